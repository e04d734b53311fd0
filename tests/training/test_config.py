"""training.config: partial files, overrides, errors naming the field, the shipped presets."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pnvlad_service.errors import InputError
from pnvlad_service.training.config import TrainConfig, parse_assignments


def test_config_file_partial_fields_and_overrides(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("model: {preset: compact, num_points: 512}\ntrain: {lr: 0.001, epochs: 3}\n")
    cfg = TrainConfig.from_file(p)
    assert cfg.model.num_points == 512 and cfg.model.cluster_size == 16
    assert cfg.train.lr == 1e-3 and cfg.train.epochs == 3 and cfg.train.negatives == 18
    cfg2 = cfg.with_overrides({"train.batch_size": 8, "model.arch": "pointnet-max", "x": None})
    assert cfg2.train.batch_size == 8 and cfg2.model.arch == "pointnet-max"
    # the dumped YAML holds every field and reads back to the same config
    assert TrainConfig.from_mapping(yaml.safe_load(cfg2.to_yaml())) == cfg2
    t = tmp_path / "c.toml"
    t.write_text("[train]\nseed = 5\n")
    assert TrainConfig.from_file(t).train.seed == 5


def test_config_errors_name_the_field(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("train: {lr: -1}\n")
    with pytest.raises(InputError, match=r"train\.lr"):
        TrainConfig.from_file(p)
    p.write_text("train: {learning_rate: 1}\n")
    with pytest.raises(InputError, match="learning_rate"):
        TrainConfig.from_file(p)
    with pytest.raises(InputError, match="unknown config field"):
        TrainConfig().with_overrides({"nope.x": 1})
    with pytest.raises(InputError):
        TrainConfig.from_file(tmp_path / "missing.yaml")
    # a dataset weight is bounded where the config is read, as every numeric field is
    for bad in ("-1", "inf"):
        with pytest.raises(InputError, match=r"data\.dataset_weights\.business"):
            TrainConfig().with_overrides(
                parse_assignments([f"data.dataset_weights={{business: {bad}}}"])
            )
    ok = TrainConfig().with_overrides(parse_assignments(["data.dataset_weights={business: 2.5}"]))
    assert ok.data.dataset_weights == {"business": 2.5}


def test_set_assignments_reach_nested_fields_as_yaml_values() -> None:
    sets = parse_assignments(
        ["model.output_dim=128", "train.augment.yaw_deg=2.5", "model.trunk_widths=[8, 16]"]
    )
    assert sets == {
        "model.output_dim": 128,
        "train.augment.yaw_deg": 2.5,
        "model.trunk_widths": [8, 16],
    }
    cfg = TrainConfig.preset("compact").with_overrides(sets)
    assert cfg.model.output_dim == 128 and cfg.train.augment.yaw_deg == 2.5
    assert tuple(cfg.model.trunk_widths) == (8, 16)
    # everything else is the preset's
    rest = cfg.with_overrides({"model.output_dim": 256, "train.augment.yaw_deg": 0.0})
    rest = rest.with_overrides(
        {"model.trunk_widths": TrainConfig.preset("compact").model.trunk_widths}
    )
    assert rest == TrainConfig.preset("compact")
    with pytest.raises(InputError, match=r"train\.augment\.nope"):
        TrainConfig().with_overrides({"train.augment.nope": 1})
    with pytest.raises(InputError, match=r"model\.output_dim"):
        TrainConfig().with_overrides({"model.output_dim.x": 1})
    with pytest.raises(InputError, match="FIELD=VALUE"):
        parse_assignments(["model.output_dim"])
    with pytest.raises(InputError, match=r"model\.output_dim"):
        TrainConfig().with_overrides(parse_assignments(["model.output_dim=[1"]))


def test_shipped_configs_load() -> None:
    paper = TrainConfig.preset("paper")
    assert paper == TrainConfig()  # paper.yaml lists exactly the defaults
    assert paper.train.lr == 5e-5 and paper.train.negatives == 18 and paper.train.positives == 2
    assert paper.model.cluster_size == 64
    assert TrainConfig.preset("compact").model.cluster_size == 16
    # The CPU recipe: the compact model with 32 clusters, in-batch mining, augmentation, the
    # cosine schedule; the same numbers as its measured run (run 16: run 8's recorded config,
    # compact-aug.yaml, with model.cluster_size=32).
    cpu = TrainConfig.preset("cpu")
    run8 = TrainConfig.from_file(Path(__file__).parents[2] / "benchmarks/configs/compact-aug.yaml")
    run16 = run8.with_overrides({"model.cluster_size": 32})
    assert cpu.model == TrainConfig.preset("compact").model.model_copy(update={"cluster_size": 32})
    assert cpu.model == run16.model
    assert cpu.train.model_copy(update={"threads": 1}) == run16.train
    assert cpu.train.augment.active and cpu.train.lr_schedule == "cosine"
    # bev: the cpu recipe's training (base: cpu) of ModelConfig.bev(), with wider margins and
    # scaling by up to 25 % (cpu: 3 %); its encoder averages three scales.
    from pnvlad_service.models.config import ModelConfig

    bev = TrainConfig.preset("bev")
    assert bev.model == ModelConfig.bev(embed_scales=(0.85, 1.0, 1.18)) and bev.data == cpu.data
    scaled = cpu.train.augment.model_copy(update={"scale": 0.25})
    assert bev.train == cpu.train.model_copy(
        update={"margin1": 1.0, "margin2": 0.5, "augment": scaled}
    )
    # bev_scan / cpu_scan: those recipes for single scans, each cloud turned to its own
    # dominant direction, trained with turns of up to 5 degrees; bev_scan (run 42) with
    # quarter-turned in-batch negatives for 10 epochs.
    extra = {"bev_scan": {"epochs": 10, "turned_negatives": True}, "cpu_scan": {}}
    for name, base in (("bev_scan", bev), ("cpu_scan", cpu)):
        scan = TrainConfig.preset(name)
        update = {"canonical_heading": True, "embed_scales": ()}
        assert scan.model == base.model.model_copy(update=update)
        # both scan recipes scale by up to 3 % and embed one scale (bev's 25 % and its three
        # scales were measured on submaps only)
        augment = base.train.augment.model_copy(update={"yaw_deg": 5.0, "scale": 0.03})
        assert scan.train == base.train.model_copy(update={"augment": augment, **extra[name]})
    with pytest.raises(InputError, match="bev, bev_scan, compact, cpu, cpu_scan, paper"):
        TrainConfig.preset("gpu")


def test_a_config_built_on_a_shipped_one(tmp_path: Path) -> None:
    """``base: cpu`` takes the cpu recipe; the fields given override one by one (the other
    fields of a section stay the base's); a model preset replaces the base's model whole."""
    p = tmp_path / "c.yaml"
    p.write_text(
        "base: cpu\ntrain: {epochs: 3, augment: {yaw_deg: 15}}\nmodel: {output_dim: 128}\n"
    )
    cfg, cpu = TrainConfig.from_file(p), TrainConfig.preset("cpu")
    assert cfg.train.epochs == 3 and cfg.train.augment.yaw_deg == 15
    assert cfg.train.augment.dropout == cpu.train.augment.dropout and cfg.train.lr == cpu.train.lr
    assert cfg.model == cpu.model.model_copy(update={"output_dim": 128})  # K = 32 kept
    p.write_text("base: cpu\nmodel: {preset: paper}\n")
    assert TrainConfig.from_file(p).model.cluster_size == 64
    p.write_text("base: nope\n")
    with pytest.raises(InputError, match="no shipped config named 'nope'"):
        TrainConfig.from_file(p)
    p.write_text("model: {preset: tiny}\n")
    with pytest.raises(InputError, match=r"model\.preset: no model preset 'tiny'") as e:
        TrainConfig.from_file(p)
    assert e.value.source == str(p)


def test_run_config_file_then_the_resumed_runs_then_the_paper(tmp_path: Path) -> None:
    from pnvlad_service.training.config import run_config

    assert run_config(None) == TrainConfig.preset("paper")
    assert run_config("compact") == TrainConfig.preset("compact")
    run = tmp_path / "run"
    assert run_config(None, run) == TrainConfig.preset("paper")  # no config.yaml yet
    run.mkdir()
    (run / "config.yaml").write_text(TrainConfig().with_overrides({"train.seed": 7}).to_yaml())
    assert run_config(None, run).train.seed == 7
    assert run_config("compact", run) == TrainConfig.preset("compact")  # a given file wins


def test_train_cli_set_reaches_the_config_and_names_a_bad_field() -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "train",
            "-c",
            "compact",
            "--set",
            "model.output_dim=128",
            "--set",
            "train.augment.dropout=0.1",
            "--lr",
            "0.002",
            "--dump-config",
        ],
    )
    assert res.exit_code == 0, res.output
    cfg = TrainConfig.from_mapping(yaml.safe_load(res.output))
    assert cfg.model.output_dim == 128 and cfg.train.augment.dropout == 0.1
    assert cfg.train.lr == 0.002 and cfg.model.cluster_size == 16  # the rest: the preset's
    # A named option wins over --set for the same field.
    res = runner.invoke(app, ["train", "--set", "train.lr=1", "--lr", "0.5", "--dump-config"])
    assert TrainConfig.from_mapping(yaml.safe_load(res.output)).train.lr == 0.5
    res = runner.invoke(app, ["train", "--set", "model.outdim=3", "--dump-config"])
    assert res.exit_code == 2 and "model.outdim" in res.output
