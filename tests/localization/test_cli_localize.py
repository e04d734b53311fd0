"""`pnvlad localize` searching a bundle locally: the table, JSON output and usage errors.
(Against a server: tests/server/test_app.py::test_pnvlad_localize_against_the_server.)"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.index import build as ix
from tests.index.helpers import PER_RUN


def local_args(world: dict[str, Path], scan: str, *more: str) -> list[str]:
    """``pnvlad localize SCAN --reader benchmark --index BUNDLE`` and ``more``."""
    return ["localize", scan, "--reader", "benchmark", "--index", str(world["bundle"]), *more]


def test_table_and_json_name_the_submap_itself_first(world: dict[str, Path]) -> None:
    rec = ix.list_database_submaps(world["tree"])[PER_RUN + 4]
    scan = str(world["tree"] / rec.path)
    runner = CliRunner()
    res = runner.invoke(app, local_args(world, scan, "-n", "4"))
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    header = ["rank", "submap", "run", "northing", "easting", "distance", "score"]
    assert lines[0].split() == header
    # No geometry in this bundle: no scores, and the verdict line says why.
    assert len(lines) == 1 + 4 + 2 and lines[-1].startswith("preprocess")
    assert lines[-2].startswith("not verified: verification off")
    assert all(ln.split()[-1] == "-" for ln in lines[1:5])
    rank1 = lines[1].split()
    assert rank1[:3] == ["1", str(rec.timestamp), rec.run]
    assert float(rank1[3]) == pytest.approx(rec.northing, abs=0.005)
    assert float(rank1[4]) == pytest.approx(rec.easting, abs=0.005)
    res = runner.invoke(app, local_args(world, scan, "-m", str(world["ckpt"]), "--json"))
    assert res.exit_code == 0, res.output
    body = json.loads(res.stdout)
    assert [m["rank"] for m in body["matches"]] == [1, 2, 3, 4, 5]
    assert body["matches"][0]["submap_id"] == rec.submap_id
    d = [m["distance"] for m in body["matches"]]
    assert d == sorted(d) and d[0] == pytest.approx(0.0, abs=1e-5)


def test_model_is_a_model_or_a_training_run_directory(
    world: dict[str, Path], tmp_path: Path
) -> None:
    """-m/--model and --checkpoint take a model directory or the training run that made it
    (OUT/model); -c is no longer a model flag anywhere."""
    run = tmp_path / "run"
    shutil.copytree(world["ckpt"], run / "model")
    rec = ix.list_database_submaps(world["tree"])[3]
    base = local_args(world, str(world["tree"] / rec.path), "--json")
    for flag, model in (("--checkpoint", run), ("--model", world["ckpt"])):
        res = CliRunner().invoke(app, [*base, flag, str(model)])
        assert res.exit_code == 0, res.output
        assert json.loads(res.stdout)["matches"][0]["submap_id"] == rec.submap_id
    res = CliRunner().invoke(app, [*base, "-c", str(world["ckpt"])])
    assert res.exit_code == 2 and "No such option: -c" in res.output
    res = CliRunner().invoke(app, [*base, "-m", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "model directory not found" in res.output


def test_usage_errors_exit_2(world: dict[str, Path], tmp_path: Path) -> None:
    runner = CliRunner()
    scan = str(world["tree"] / ix.list_database_submaps(world["tree"])[0].path)
    res = runner.invoke(app, ["localize", scan, "--reader", "benchmark"])
    assert res.exit_code == 2 and "--url" in res.output
    res = runner.invoke(app, local_args(world, scan, "--url", "http://127.0.0.1:1"))
    assert res.exit_code == 2
    raw = tmp_path / "raw.npy"
    np.save(raw, np.random.default_rng(0).uniform(-30, 30, (1000, 3)))
    res = runner.invoke(app, ["localize", str(raw), "--index", str(world["bundle"])])
    assert res.exit_code == 2 and "preprocess" in res.output
    res = runner.invoke(
        app, ["localize", scan, "--reader", "benchmark", "--url", "http://127.0.0.1:9"]
    )
    assert res.exit_code == 2 and "cannot reach" in res.output
    res = runner.invoke(app, local_args({"bundle": tmp_path / "none"}, scan))
    assert res.exit_code == 2 and "not found" in res.output
    res = runner.invoke(app, ["localize", "--mode", "follow", "--index", str(world["bundle"])])
    assert res.exit_code == 2 and "--mode: --mode follow needs a drive: --rosbag" in res.output


def test_mode_scan_is_the_old_spelling(world: dict[str, Path]) -> None:
    """`pnvlad localize --mode scan SCAN` answers what `pnvlad localize SCAN` answers."""
    rec = ix.list_database_submaps(world["tree"])[PER_RUN + 2]
    scan = str(world["tree"] / rec.path)
    answers = []
    for extra in ([], ["--mode", "scan"]):
        res = CliRunner().invoke(app, [*local_args(world, scan, "--json", "-n", "3"), *extra])
        assert res.exit_code == 0, res.output
        answers.append(json.loads(res.stdout))
    old, new = ([(m["submap_id"], m["distance"]) for m in a["matches"]] for a in answers)
    assert old == new and old[0][0] == rec.submap_id


def test_the_verification_settings_apply_to_a_local_search(tiny_maps: dict) -> None:
    """--verify-stop-score and --verify-threshold set the local verification (docs/VERIFY.md:
    a stricter stop for push-broom maps); a server and a drive refuse them."""
    tree, run = tiny_maps["tree"], tiny_maps["query_run"]
    sub = tree.submaps("business", run, "test")[2]
    scale = abs(tree.frames("business", run, "test")[2].scale)  # one pass, rigid
    base = ["localize", str(tree.root / sub.path), "--reader", "benchmark", "--json",
            "--index", str(tiny_maps["map"]), "--scale", f"{scale:.6f}"]  # fmt: skip

    def verification(*more: str) -> dict:
        res = CliRunner().invoke(app, [*base, *more])
        assert res.exit_code == 0, res.output
        return json.loads(res.stdout)["verification"]

    every = verification("--verify-stop-score", "1")
    first = verification("--verify-stop-score", "0")
    assert every["registered"] == every["candidates"] == 10  # nothing scores 1: all registered
    assert first["registered"] < every["registered"]
    assert verification()["threshold"] == pytest.approx(0.09)
    strict = verification("--verify-threshold", "0.999")
    assert strict["threshold"] == pytest.approx(0.999)
    res = CliRunner().invoke(app, [*base, "--verify-stop-score", "1.5"])
    assert res.exit_code == 2 and "--verify-stop-score" in res.output
    url = [
        "localize",
        str(tree.root / sub.path),
        "--reader",
        "benchmark",
        "--url",
        "http://127.0.0.1:9",
    ]
    for flag in ("--verify-stop-score", "--verify-threshold"):
        res = CliRunner().invoke(app, [*url, flag, "0.4"])
        assert res.exit_code == 2 and f"{flag}: applies to --index" in res.output
    res = CliRunner().invoke(
        app,
        ["localize", "--kitti", str(tree.root), "--index", str(tiny_maps["keys"]),
         "--verify-stop-score", "0.4"],
    )  # fmt: skip
    assert res.exit_code == 2 and "--verify-stop-score: applies to a single scan" in res.output
