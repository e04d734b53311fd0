"""The models that ship with pnvlad (``pnvlad_service/pretrained/``): each, as a user loads it by
name through ``pnvlad eval``, reproduces the recall@1 its catalogue entry records on the
``tiny`` city generated here, and stands far above the same network with random weights there.
A model stored or loaded wrong (weights in the wrong layers, the float16 copy off, a change of
preprocessing the shipped weights were not trained for) fails the first; weights that were
never trained fail the second."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.models import pretrained

SHIPPED = pretrained.Catalogue.read(pretrained.PACKAGE_CATALOGUE).entries
# The tiny city has 42 queries: one query's share of recall@1 (a tie decided another way on
# another CPU) is what the recorded figure may move by.
ONE_QUERY = 100.0 / 42 + 0.01
# A random bev-netvlad finds 29-38 % of the tiny city's places (two seeds of each kind); the
# shipped ones 71-74 %.
ABOVE_RANDOM = 20.0


def _tiny_figure(entry: pretrained.Entry) -> float:
    key = "recall@1 (tiny --seed 3)" if entry.kind == "submap" else "recall@1 (tiny --seed 3 scans)"
    return float(entry.figures[key])


def _eval(model: str, tiny: Path, kind: str, out: Path) -> float:
    splits = "splits.json" if kind == "submap" else "splits_keyframes.json"
    args = ["eval", "-m", model, "--root", str(tiny), "--splits", str(tiny / splits)]
    args += ["-o", str(out)] + (["--queries", "scans"] if kind == "scan" else [])
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return float(json.loads(out.read_text())["recall_at_1"])


@pytest.mark.parametrize("entry", SHIPPED, ids=lambda e: e.name)
def test_a_shipped_model_reproduces_its_recorded_figure(
    entry: pretrained.Entry, tiny: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(pretrained.CATALOGUE_ENV, raising=False)
    got = _eval(f"pretrained:{entry.name}", tiny, entry.kind, tmp_path / "eval.json")
    assert abs(got - _tiny_figure(entry)) <= ONE_QUERY, (entry.name, got)


@pytest.mark.parametrize("entry", SHIPPED, ids=lambda e: e.name)
def test_a_shipped_model_is_far_above_its_network_with_random_weights(
    entry: pretrained.Entry, tiny: Path, tmp_path: Path
) -> None:
    import torch

    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import read_model_json, save_model

    cfg, _ = read_model_json(
        pretrained.resolve(f"pretrained:{entry.name}", pretrained.PACKAGE_CATALOGUE)
    )
    torch.manual_seed(0)
    random_dir = save_model(tmp_path / "random", build_model(cfg), cfg)
    chance = _eval(str(random_dir), tiny, entry.kind, tmp_path / "random.json")
    assert _tiny_figure(entry) - chance >= ABOVE_RANDOM, (entry.name, chance)
