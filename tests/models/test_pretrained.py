"""Pretrained models by name: packaging a trained model into a catalogue (float16 storage, its
ONNX file, sizes, atomic writes), resolving ``pretrained:NAME`` wherever a model is taken, and
the errors for an unknown name and for corrupt files. Every test uses its own catalogue in a
temporary folder (``PNVLAD_PRETRAINED``), never the package's."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.errors import InputError
from pnvlad_service.models import pretrained
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.packaging import Card, package_model
from pnvlad_service.models.pretrained import Catalogue
from pnvlad_service.models.store import load_model, model_identity, resolve_model_dir, save_model
from tests.models.helpers import BEV_SMALL, CONFIGS, trained_like

CARD = Card(
    kind="submap",
    trained_with="pnvlad train -c bev --root city -o run",
    data="a test model",
    figures={"recall@1": 12.5},
)


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


@pytest.fixture()
def catalogue(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty catalogue of its own, the one every command reads in this test."""
    path = tmp_path / "pretrained" / "catalogue.json"
    path.parent.mkdir()
    path.write_text(json.dumps({"format": "pnvlad-pretrained", "version": 1, "models": []}))
    monkeypatch.setenv(pretrained.CATALOGUE_ENV, str(path))
    return path


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small bev-netvlad with non-trivial weights and batch norms, saved as a run would."""
    model = trained_like(BEV_SMALL, seed=3)
    return save_model(tmp_path_factory.mktemp("run") / "model", model, BEV_SMALL)


@pytest.fixture()
def packaged(trained: Path, catalogue: Path) -> pretrained.Entry:
    return package_model(trained, "bev-test", CARD)


def test_package_records_every_file_as_it_is_on_disk(
    packaged: pretrained.Entry, catalogue: Path
) -> None:
    doc = json.loads(catalogue.read_text())
    assert [m["name"] for m in doc["models"]] == ["bev-test"]
    entry = doc["models"][0]
    folder = catalogue.parent / entry["dir"]
    assert set(entry["files"]) == {"model.json", "model.safetensors", "model.onnx"}
    assert {p.name for p in folder.iterdir()} == set(entry["files"])
    for name, rec in entry["files"].items():
        data = (folder / name).read_bytes()
        assert rec == {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    assert entry["kind"] == "submap" and entry["encoder"] == "bev-netvlad"
    assert entry["dtype"] == "float16"
    assert entry["trained_with"] == CARD.trained_with and entry["figures"] == CARD.figures
    # nothing left behind under a temporary name
    assert sorted(p.name for p in catalogue.parent.iterdir()) == ["bev-test", "catalogue.json"]


def test_matrices_are_stored_as_float16_and_load_as_float32(
    packaged: pretrained.Entry, trained: Path
) -> None:
    directory = resolve_model_dir("pretrained:bev-test")
    original, _ = load_model(trained)
    with safe_open(str(directory / "model.safetensors"), "pt") as f:
        dtypes = {k: (f.get_tensor(k).dtype, f.get_tensor(k).dim()) for k in f.keys()}  # noqa: SIM118
    assert {d for d, dim in dtypes.values() if dim >= 2} == {torch.float16}
    assert {d for d, dim in dtypes.values() if dim < 2} <= {torch.float32, torch.int64}
    size = (directory / "model.safetensors").stat().st_size
    full = (trained / "model.safetensors").stat().st_size
    matrices = sum(
        v.numel() * 4
        for v in original.state_dict().values()
        if v.is_floating_point() and v.dim() > 1
    )
    assert abs(size - (full - matrices // 2)) <= 256  # half the matrices' bytes (header aside)
    model, _ = load_model(directory)
    want_state = original.state_dict()
    assert list(model.state_dict()) == list(want_state)
    for k, got in model.state_dict().items():
        want = want_state[k]
        assert got.dtype == want.dtype, k
        if got.is_floating_point():
            # each value is the float16 rounding of the original (or the original itself)
            assert torch.allclose(got, want, rtol=2**-10, atol=1e-7), k


def test_stored_descriptors_stay_close_in_torch_and_in_onnx(
    packaged: pretrained.Entry, trained: Path
) -> None:
    from pnvlad_service.models.runtimes import open_encoder

    x = np.random.default_rng(0).uniform(-1, 1, (24, 256, 3)).astype(np.float32)
    want = Encoder.from_checkpoint(trained).embed(x)
    got = open_encoder("pretrained:bev-test", runtime="torch").embed(x)
    # the functions that read a directory as given take the name too (eval, benchmarks)
    assert np.array_equal(Encoder.from_checkpoint("pretrained:bev-test").embed(x), got)
    ort = open_encoder("pretrained:bev-test", runtime="onnx", threads=1)
    try:
        onnx_got = ort.embed(x)
    finally:
        ort.close()
    assert _cosines(got, want).min() >= 0.999
    assert not np.array_equal(got, want)  # the stored weights are really rounded
    assert _cosines(onnx_got, got).min() >= 0.9999
    fid = packaged.extra["fidelity"]
    assert fid["clouds"] == 64 and fid["min_cosine"] >= 0.999
    assert packaged.extra["onnx_min_cosine"] >= 0.9999


def test_onnx_weights_are_float16_in_the_file(packaged: pretrained.Entry) -> None:
    import onnx

    proto = onnx.load(str(resolve_model_dir("pretrained:bev-test") / "model.onnx"))
    big = [t for t in proto.graph.initializer if len(t.dims) >= 2]
    assert big and {t.data_type for t in big} == {onnx.TensorProto.FLOAT16}


def test_model_identity_and_index_build_take_the_name(
    packaged: pretrained.Entry, tmp_path: Path, tiny: Path
) -> None:
    identity = model_identity("pretrained:bev-test")
    assert identity.weights_sha256 == packaged.files["model.safetensors"].sha256
    out = tmp_path / "map.index"
    res = CliRunner().invoke(
        app,
        ["index", "build", "-m", "pretrained:bev-test", "-r", str(tiny), "-o", str(out)],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["model"]["weights_sha256"] == identity.weights_sha256
    # and the map answers with the model named the same way (localize, as serve loads it)
    from pnvlad_service.index.build import list_database_submaps

    rec = list_database_submaps(tiny)[5]
    args = ["localize", str(tiny / rec.path), "--reader", "benchmark", "--index", str(out)]
    answers = []
    for model in ("pretrained:bev-test", str(resolve_model_dir("pretrained:bev-test"))):
        res = CliRunner().invoke(app, [*args, "-m", model, "--json"])
        assert res.exit_code == 0, res.output
        answers.append([m["submap_id"] for m in json.loads(res.stdout)["matches"]])
    assert answers[0] == answers[1] and len(answers[0]) == 5


def test_an_unknown_name_lists_the_known_ones(packaged: pretrained.Entry) -> None:
    with pytest.raises(InputError, match=r"pretrained:nope: unknown .*known: bev-test"):
        resolve_model_dir("pretrained:nope")
    res = CliRunner().invoke(app, ["model", "info", "pretrained:nope"])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "known: bev-test" in lines[0], res.output


def test_a_bare_name_points_to_the_prefix(packaged: pretrained.Entry, tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"did you mean pretrained:bev-test\?"):
        resolve_model_dir("bev-test")


@pytest.mark.parametrize("victim", ["model.safetensors", "model.onnx", "model.json"])
def test_a_corrupt_file_is_named_and_nothing_loads(
    packaged: pretrained.Entry, catalogue: Path, victim: str
) -> None:
    path = catalogue.parent / "bev-test" / victim
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as err:
        resolve_model_dir("pretrained:bev-test")
    assert err.value.source == str(path) and "SHA-256" in str(err.value)
    for args in (["model", "info", "pretrained:bev-test"], ["model", "list"]):
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2, args
        errors = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1 and str(path) in errors[0], res.output


def test_a_truncated_file_is_named(packaged: pretrained.Entry, catalogue: Path) -> None:
    path = catalogue.parent / "bev-test" / "model.safetensors"
    path.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(InputError, match="bytes, the catalogue records") as err:
        resolve_model_dir("pretrained:bev-test")
    assert err.value.source == str(path)


def test_list_prints_each_model_with_its_check(packaged: pretrained.Entry) -> None:
    res = CliRunner().invoke(app, ["model", "list"])
    assert res.exit_code == 0, res.output
    line = next(ln for ln in res.output.splitlines() if "pretrained:bev-test" in ln)
    assert "submap" in line and "bev-netvlad" in line and "float16" in line
    assert "sha256 OK" in line and "recall@1 12.5" in line
    doc = json.loads(CliRunner().invoke(app, ["model", "list", "--json"]).output)
    assert doc["models"][0]["verified"] is True
    assert doc["models"][0]["bytes"] == packaged.bytes
    info = CliRunner().invoke(app, ["model", "info", "bev-test", "--json"])
    assert info.exit_code == 0, info.output
    assert json.loads(info.output)["pretrained"]["name"] == "bev-test"


def test_over_the_size_limit_writes_nothing(trained: Path, catalogue: Path) -> None:
    before = catalogue.read_bytes()
    with pytest.raises(InputError, match="over the limit of"):
        package_model(trained, "big", CARD, max_model_bytes=1000)
    package_model(trained, "first", CARD, onnx=False)
    with pytest.raises(InputError, match="for all of them"):
        package_model(trained, "second", CARD, onnx=False, max_total_bytes=Catalogue.read().bytes)
    assert Catalogue.read().names == ["first"]
    assert sorted(p.name for p in catalogue.parent.iterdir()) == ["catalogue.json", "first"]
    assert catalogue.read_bytes() != before  # "first" went in


def test_a_name_is_packaged_once_unless_replaced(trained: Path, catalogue: Path) -> None:
    package_model(trained, "bev-test", CARD, float16=False, onnx=False)
    with pytest.raises(InputError, match="already in the catalogue"):
        package_model(trained, "bev-test", CARD)
    package_model(trained, "after", CARD, float16=False, onnx=False)
    entry = package_model(trained, "bev-test", CARD, onnx=False, overwrite=True)
    # replaced where it stood, not moved to the end of the list
    assert entry.dtype == "float16" and Catalogue.read().names == ["bev-test", "after"]
    for bad, field in [("Bev_Test", "name"), ("../up", "name")]:
        with pytest.raises(InputError) as err:
            package_model(trained, bad, CARD)
        assert err.value.source == field
    with pytest.raises(InputError) as err:
        package_model(trained, "x", Card(kind="drive"))
    assert err.value.source == "kind"


def test_a_malformed_catalogue_is_named(catalogue: Path) -> None:
    catalogue.write_text('{"format": "pnvlad-pretrained", "version": 1, "models": [{"name": 3}]}')
    with pytest.raises(InputError) as err:
        resolve_model_dir("pretrained:x")
    assert err.value.source == str(catalogue)
    catalogue.write_text("{")
    res = CliRunner().invoke(app, ["model", "list"])
    assert res.exit_code == 2 and str(catalogue) in res.output
    catalogue.unlink()  # named by PNVLAD_PRETRAINED: missing is an error, not an empty list
    res = CliRunner().invoke(app, ["model", "list"])
    assert res.exit_code == 2 and "no such pretrained catalogue file" in res.output


def test_the_cli_packages_with_figures(trained: Path, catalogue: Path) -> None:
    res = CliRunner().invoke(
        app,
        [
            "model", "package", str(trained), "--name", "bev-cli", "--no-onnx",
            "--figure", "recall@1 (benchmark)=97.5", "--figure", "note=five runs",
            "--trained-with", "pnvlad train -c bev", "--data", "benchmark seed 1",
        ],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    entry = Catalogue.read().get("bev-cli")
    assert entry.figures == {"recall@1 (benchmark)": 97.5, "note": "five runs"}
    assert set(entry.files) == {"model.json", "model.safetensors"}
    res = CliRunner().invoke(
        app, ["model", "package", str(trained), "--name", "x", "--figure", "novalue"]
    )
    assert res.exit_code == 2 and "--figure" in res.output


def test_embed_scales_are_set_at_packaging_and_embed_by_them(
    trained: Path, catalogue: Path
) -> None:
    """``--embed-scales``: the packaged model's config carries them, it embeds as the source
    with them would (and not as the source as trained), the catalogue entry's files match; a
    bad value is one error naming the option and nothing is written."""
    res = CliRunner().invoke(
        app,
        ["model", "package", str(trained), "--name", "bev-ms", "--no-onnx",
         "--embed-scales", "0.8,1,1.25"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    model, cfg = load_model(resolve_model_dir("pretrained:bev-ms"))
    assert cfg.embed_scales == (0.8, 1.0, 1.25)
    source, source_cfg = load_model(trained)
    x = np.random.default_rng(3).uniform(-0.6, 0.6, (4, 256, 3)).astype(np.float32)
    scaled_cfg = source_cfg.model_copy(update={"embed_scales": (0.8, 1.0, 1.25)})
    got = Encoder(model, cfg).embed(x)
    assert _cosines(got, Encoder(source, scaled_cfg).embed(x)).min() > 0.999
    want = sum(Encoder(source, source_cfg).embed(x * s) for s in (0.8, 1.0, 1.25))
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert _cosines(got, want).min() > 0.999
    for bad, says in (("0.8,x", "--embed-scales"), ("0.1,1", "embed_scales")):
        res = CliRunner().invoke(
            app,
            ["model", "package", str(trained), "--name", "bev-bad", "--embed-scales", bad],
        )
        assert res.exit_code != 0 and says in res.output, res.output
        assert "bev-bad" not in [e.name for e in Catalogue.read().entries]
        assert not (catalogue.parent / "bev-bad").exists()


def test_the_models_verification_threshold_goes_with_it(
    trained: Path, catalogue: Path, tmp_path: Path
) -> None:
    import shutil

    from pnvlad_service.localization.query.calibration import (
        Calibration,
        read_calibration,
        write_calibration,
    )
    from pnvlad_service.models.store import weights_sha256

    run = tmp_path / "calibrated"
    shutil.copytree(trained, run)
    cal = Calibration(0.25, weights_sha256(run), 10, 99.0, 50, {"precision": 99.5})
    write_calibration(run, cal)
    entry = package_model(run, "with-threshold", CARD, onnx=False)
    assert "verification.json" in entry.files
    stored = resolve_model_dir("pretrained:with-threshold")
    got = read_calibration(stored, weights_sha256(stored))
    assert got is not None and got.threshold == 0.25 and got.candidates == 10
    # a record chosen for other weights stays behind
    write_calibration(run, Calibration(0.3, "0" * 64, 10, 99.0, 50, {}))
    entry = package_model(run, "stale", CARD, onnx=False)
    assert "verification.json" not in entry.files


def test_only_matrices_within_float16s_range_are_halved() -> None:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from pnvlad_service.models.onnx_export import store_float16
    from pnvlad_service.models.packaging import half_state

    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 2))
    with torch.no_grad():
        model[1].weight[0, 0] = 1e6  # beyond float16's 65504
    state = half_state(model)
    assert state["0.weight"].dtype == torch.float16
    assert state["1.weight"].dtype == torch.float32 and state["0.bias"].dtype == torch.float32

    rng = np.random.default_rng(0)
    w = rng.normal(size=(3, 4)).astype(np.float32)
    big = np.full((4, 2), 1e6, dtype=np.float32)
    inits = [
        numpy_helper.from_array(w, "w"),
        numpy_helper.from_array(big, "big"),
        numpy_helper.from_array(np.ones(2, np.float32), "b"),
    ]
    nodes = [
        helper.make_node("MatMul", ["x", "w"], ["h"]),
        helper.make_node("MatMul", ["h", "big"], ["m"]),
        helper.make_node("Add", ["m", "b"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])],
        inits,
    )
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    assert store_float16(proto) == 1
    onnx.checker.check_model(proto)
    types = {t.name: t.data_type for t in proto.graph.initializer}
    assert types == {
        "w__f16": TensorProto.FLOAT16,
        "big": TensorProto.FLOAT,
        "b": TensorProto.FLOAT,
    }
    import onnxruntime as ort

    x = rng.normal(size=(1, 3)).astype(np.float32)
    sess = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    want = x @ w.astype(np.float16).astype(np.float32) @ big + 1
    np.testing.assert_allclose(sess.run(None, {"x": x})[0], want, rtol=1e-5)


def test_export_does_not_rewrite_a_pretrained_model(packaged: pretrained.Entry) -> None:
    res = CliRunner().invoke(app, ["model", "export", "pretrained:bev-test"])
    assert res.exit_code == 2 and "copy its directory" in res.output
    assert Catalogue.read().problems(packaged) == []


def test_a_model_of_fewer_points_is_checked_on_full_submaps(
    tmp_path: Path, catalogue: Path
) -> None:
    """A PointNetVLAD trained on fewer points than a submap holds (``--num-points 1024``) is
    checked on its seeded clouds of that size and on the check tree's 4,096-point submaps, as
    the index and the server embed them: every cloud counted, the float16 copy within the
    bound, and the stored model embeds both sizes as the original does."""
    cfg = CONFIGS["compact"]  # 256 points
    source = save_model(tmp_path / "run" / "model", trained_like(cfg, seed=4), cfg)
    rng = np.random.default_rng(0)
    submaps = rng.uniform(-1, 1, (5, 4096, 3)).astype(np.float32)
    entry = package_model(source, "pn-small", CARD, onnx=False, points=submaps)
    assert entry.extra["fidelity"]["clouds"] == 64 + 5
    assert entry.extra["fidelity"]["min_cosine"] >= 0.999
    stored = Encoder.from_checkpoint(pretrained.resolve("pretrained:pn-small"))
    original = Encoder.from_checkpoint(source)
    for n in (256, 4096):
        clouds = rng.uniform(-1, 1, (3, n, 3)).astype(np.float32)
        assert _cosines(stored.embed(clouds), original.embed(clouds)).min() >= 0.999


def test_a_serving_only_catalogue_embeds_and_answers_as_the_full_one(
    packaged: pretrained.Entry, catalogue: Path, tmp_path: Path, tiny: Path
) -> None:
    """The server image's models: weights left out, ONNX Runtime embeds, and a map indexed with
    the full model still answers with them (the same identity)."""
    from pnvlad_service.index.build import list_database_submaps
    from pnvlad_service.models.runtimes import open_encoder

    x = np.random.default_rng(1).uniform(-1, 1, (8, 256, 3)).astype(np.float32)
    full = open_encoder("pretrained:bev-test", runtime="onnx", threads=1)
    want = full.embed(x)
    full.close()
    identity = model_identity("pretrained:bev-test")
    out = tmp_path / "map.index"
    res = CliRunner().invoke(
        app, ["index", "build", "-m", "pretrained:bev-test", "-r", str(tiny), "-o", str(out)]
    )
    assert res.exit_code == 0, res.output

    directory = catalogue.parent / "bev-test"
    assert pretrained.make_serving_only() == [directory / "model.safetensors"]
    assert sorted(p.name for p in directory.iterdir()) == ["model.json", "model.onnx"]
    assert set(Catalogue.read().get("bev-test").files) == {"model.json", "model.onnx"}
    assert resolve_model_dir("pretrained:bev-test") == directory  # every listed file verifies
    # torch is installed here, yet auto takes ONNX Runtime: there are no weights for torch
    enc = open_encoder("pretrained:bev-test", threads=1)
    try:
        assert enc.runtime == "onnx" and np.array_equal(enc.embed(x), want)
    finally:
        enc.close()
    assert model_identity("pretrained:bev-test").weights_sha256 == identity.weights_sha256
    with pytest.raises(InputError, match="serving-only directory"):
        open_encoder("pretrained:bev-test", runtime="torch")
    rec = list_database_submaps(tiny)[5]
    res = CliRunner().invoke(
        app,
        ["localize", str(tiny / rec.path), "--reader", "benchmark", "--index", str(out),
         "-m", "pretrained:bev-test", "--json"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert len(json.loads(res.stdout)["matches"]) == 5
    assert pretrained.make_serving_only() == []  # once is enough


@pytest.mark.parametrize("case", ["corrupt onnx", "no onnx"])
def test_serving_only_refuses_a_model_it_cannot_serve_and_changes_nothing(
    trained: Path, catalogue: Path, case: str
) -> None:
    package_model(trained, "good", CARD)
    if case == "no onnx":
        package_model(trained, "bad", CARD, onnx=False)
        named, why = catalogue.parent / "bad", "has no model.onnx"
    else:
        package_model(trained, "bad", CARD)
        named, why = catalogue.parent / "bad" / "model.onnx", "SHA-256 differs"
        data = bytearray(named.read_bytes())
        data[len(data) // 2] ^= 0xFF
        named.write_bytes(bytes(data))
    before = catalogue.read_bytes()
    with pytest.raises(InputError, match=why) as err:
        pretrained.make_serving_only()
    assert err.value.source == str(named)
    assert catalogue.read_bytes() == before
    for name in ("good", "bad"):
        assert (catalogue.parent / name / "model.safetensors").is_file()
