"""Evaluation: recall on hand-made cases with known descriptors, the JSON report, figures."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.dataset import EvalRun
from pnvlad_service.errors import InputError
from pnvlad_service.evaluation import evaluate
from tests.training.street import make_tiny_tree, tiny_config


def mean_embedder(points: np.ndarray) -> np.ndarray:
    """A fixed "encoder": the mean point of each cloud (float32 [B, 3])."""
    return points.mean(axis=1).astype(np.float32)


def write_cloud(path: Path, code: np.ndarray) -> Path:
    """A .npy submap whose mean point is ``code`` (so its mean_embedder descriptor is known)."""
    rng = np.random.default_rng(abs(hash(path.name)) % 2**32)
    pts = rng.normal(scale=0.05, size=(64, 3))
    pts = pts - pts.mean(0) + code
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, pts.astype(np.float64))
    return path


def hand_case(tmp: Path, confuse: bool = True) -> tuple[list[EvalRun], dict]:
    """3 runs along a line, submaps every 20 m at northings 0..180; every submap is a query.
    Descriptors encode the position, except run 2's submaps at 100 m and 140 m, which look like
    the place 60 m further on. Returns the runs and the descriptors by (run, k)."""
    runs = []
    desc = {}
    north = np.arange(10) * 20.0
    for r in range(3):
        paths = []
        for k, n in enumerate(north):
            code = np.array([n / 100.0, 0.1 * r / 100.0, 0.0])
            if confuse and r == 2 and n in (100.0, 140.0):
                code[0] = (n + 60.0) / 100.0
                code[1] += 0.0005  # no exact tie with the real place 60 m on
            desc[(r, k)] = code
            paths.append(write_cloud(tmp / f"run{r}" / f"{k}.npy", code))
        xy = np.stack([north, np.zeros(10)], axis=1)
        runs.append(EvalRun(f"run{r}", paths, xy, list(paths), xy.copy(), [], area="line"))
    for j, run in enumerate(runs):
        run.truth = [
            {i: np.flatnonzero(np.abs(north - north[q]) <= 25.0) for i in range(3) if i != j}
            for q in range(10)
        ]
    return runs, desc


def expected_recall(runs: list[EvalRun], desc: dict) -> tuple[list[float], float]:
    """recall@1..25 and @1% by a plain loop over pairs and queries (no FAISS, no metrics.py)."""
    per_pair_n, per_pair_pct = [], []
    for i in range(len(runs)):
        for j in range(len(runs)):
            if i == j:
                continue
            db_size = len(runs[i].db_paths)
            n_pct = max(round(db_size / 100), 1)
            hits = [0] * 25
            pct = 0
            count = 0
            for q in range(len(runs[j].query_paths)):
                true = set(runs[j].truth[q][i].tolist())
                if not true:
                    continue
                count += 1
                dists = []
                for k in range(db_size):
                    d = sum(
                        (float(desc[(j, q)][c]) - float(desc[(i, k)][c])) ** 2 for c in range(3)
                    )
                    dists.append((d, k))
                ranked = [k for _, k in sorted(dists)]
                for n in range(25):
                    if any(k in true for k in ranked[: n + 1]):
                        hits[n] += 1
                pct += any(k in true for k in ranked[:n_pct])
            per_pair_n.append([100.0 * h / count for h in hits])
            per_pair_pct.append(100.0 * pct / count)
    return list(np.mean(per_pair_n, axis=0)), float(np.mean(per_pair_pct))


def test_recall_matches_plain_loop(tmp_path: Path) -> None:
    runs, desc = hand_case(tmp_path)
    rep = evaluate.evaluate_runs(mean_embedder, runs, 64, progress=False, joint=True)
    exp_n, exp_pct = expected_recall(runs, desc)
    assert rep["recall_at_n"] == pytest.approx(exp_n)
    assert rep["recall_at_1pct"] == pytest.approx(exp_pct)
    # Hand-worked: only the 2 pairs where run 2 gives the queries lose anything at N = 1: its two
    # confused submaps are wrong, 2 of 10 queries; as a database run 2 still ranks the true
    # place first (0.002 closer than the confused one).
    assert rep["recall_at_1"] == pytest.approx(100 - 2 * 20 / 6)
    assert rep["n_pairs"] == 6
    assert rep["n_unique_submaps"] == 30  # every query is also a database submap: embedded once
    assert rep["per_area"]["line"]["recall_at_1"] == pytest.approx(rep["recall_at_1"])
    # recall@1 by distance: at 25 m it is recall@1 (the ground-truth radius); the wrong top-1s
    # lie 40 m (140 -> 180) and 60 m (100 -> 160) away, so 50 m forgives one of them.
    th = rep["distance_thresholds_m"]
    by_d = dict(zip(th, rep["recall_at_1_by_distance"], strict=True))
    assert by_d[25.0] == pytest.approx(rep["recall_at_1"])
    assert by_d[50.0] == pytest.approx(100 - 20 / 6)
    assert by_d[2.5] < by_d[25.0]
    shares = {q["run"]: q["top1_correct_share"] for q in rep["queries"]}
    assert shares["run2"][5] == 0.0 and shares["run0"][0] == 1.0
    j = rep["joint"]
    assert j["n_db"] == 30 and j["n_queries"] == 30
    assert 0 < j["recall_at_1"] < 100


def test_perfect_descriptors_give_full_recall(tmp_path: Path) -> None:
    runs, _ = hand_case(tmp_path, confuse=False)
    rep = evaluate.evaluate_runs(mean_embedder, runs, 64, progress=False)
    assert rep["recall_at_1"] == pytest.approx(100.0)
    assert rep["recall_at_1pct"] == pytest.approx(100.0)


def test_queries_without_truth_are_skipped(tmp_path: Path) -> None:
    runs, desc = hand_case(tmp_path)
    for run in runs:  # queries 0..4 lose their ground truth
        for q in range(5):
            run.truth[q] = {i: np.zeros(0, dtype=np.int64) for i in run.truth[q]}
    rep = evaluate.evaluate_runs(mean_embedder, runs, 64, progress=False)
    exp_n, _ = expected_recall(runs, desc)
    assert rep["n_queries_evaluated"] == 6 * 5
    assert rep["recall_at_n"] == pytest.approx(exp_n)


def test_report_json_round_trip_and_figures(tmp_path: Path) -> None:
    runs, _ = hand_case(tmp_path / "data")
    rep = evaluate.evaluate_runs(
        mean_embedder, runs, 64, progress=False, encoder_info={"kind": "test"}
    )
    path = evaluate.write_report(rep, tmp_path / "out" / "report.json")
    back = evaluate.read_report(path)
    for key in (
        "format",
        "version",
        "encoder",
        "recall_at_n",
        "recall_at_1",
        "recall_at_1pct",
        "per_area",
        "per_pair",
        "queries",
        "n_db",
        "n_queries",
        "runs",
    ):
        assert key in back
    assert len(back["recall_at_n"]) == 25
    assert back["encoder"] == {"kind": "test"}
    assert json.loads(path.read_text())["recall_at_1"] == pytest.approx(rep["recall_at_1"])
    pytest.importorskip("matplotlib")
    png = evaluate.plot_recall_curves([("a", back), ("b", back)], tmp_path / "out" / "r.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    png2 = evaluate.plot_query_map(back, tmp_path / "out" / "map.png")
    assert png2.stat().st_size > 1000


def test_bad_inputs(tmp_path: Path) -> None:
    runs, _ = hand_case(tmp_path)
    with pytest.raises(InputError):
        evaluate.evaluate_runs(mean_embedder, runs[:1], 64, progress=False)
    (tmp_path / "x.json").write_text('{"format": "other"}')
    with pytest.raises(InputError):
        evaluate.read_report(tmp_path / "x.json")


def test_real_model_path_on_tiny_model(tmp_path: Path) -> None:
    """A tiny real network through module_embedder: descriptors of unit norm, recall in range."""
    torch = pytest.importorskip("torch")
    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.embedding import module_embedder
    from pnvlad_service.models.factory import build_model

    runs, _ = hand_case(tmp_path)
    torch.manual_seed(0)
    cfg = ModelConfig.compact(num_points=64, cluster_size=4, output_dim=16)
    model = build_model(cfg)
    emb = module_embedder(model)
    d = evaluate.embed_paths(emb, runs[0].db_paths, 64, chunk=3)
    assert d.shape == (10, 16) and d.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4)
    rep = evaluate.evaluate_runs(emb, runs, 64, progress=False)
    assert 0.0 <= rep["recall_at_1"] <= rep["recall_at_n"][-1] <= 100.0


# ---------------------------------------------------------------------------------------------
# the commands, end to end on a tiny tree


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A tiny tree with splits and a 2-step training run through `pnvlad train`."""
    pytest.importorskip("torch")
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    root = tmp_path_factory.mktemp("evaltree")
    splits = make_tiny_tree(root, runs=3, train_step=10.0)
    cfg = root / "tiny.yaml"
    cfg.write_text(tiny_config(root, splits).to_yaml())
    run = root / "run"
    res = CliRunner().invoke(
        app, ["-q", "train", "-c", str(cfg), "-o", str(run), "--max-steps", "2", "--no-progress"]
    )
    assert res.exit_code == 0, res.output
    assert "2 steps" in res.output
    return root, splits, run


def test_cli_eval_checkpoint_report_and_figures(
    trained: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    root, splits, run = trained
    out = tmp_path / "rep.json"
    res = CliRunner().invoke(
        app,
        [
            "-q",
            "eval",
            "--checkpoint",
            str(run),
            "--root",
            str(root),
            "--splits",
            str(splits),
            "-o",
            str(out),
            "--joint",
            "--no-progress",
        ]
        + (["--figures", str(tmp_path / "fig")] if _has_matplotlib() else []),
    )
    assert res.exit_code == 0, res.output
    rep = evaluate.read_report(out)
    assert rep["n_runs"] == 3 and rep["n_pairs"] == 6
    assert rep["encoder"]["kind"] == "checkpoint" and len(rep["encoder"]["weights_sha256"]) == 64
    assert rep["n_unique_submaps"] == rep["n_db"]  # queries are database submaps: embedded once
    assert 0 <= rep["recall_at_1"] <= 100
    # 30 submaps a database: the 1% cut-off is N = max(round(0.3), 1) = 1
    assert rep["recall_at_1pct"] == pytest.approx(rep["recall_at_1"])
    assert rep["recall_at_n"] == sorted(rep["recall_at_n"])  # cumulative
    assert "joint" in rep and rep["joint"]["n_queries"] > 0
    assert rep["encoder"]["path"] == str(run / "model")  # the run directory's final model
    assert f"recall@1 {rep['recall_at_1']:.2f}" in res.output
    if _has_matplotlib():
        assert (tmp_path / "fig" / "recall_at_n.png").is_file()
        assert (tmp_path / "fig" / "query_map.png").is_file()
        res2 = CliRunner().invoke(
            app,
            [
                "-q",
                "eval",
                "--plot",
                str(out),
                "--plot",
                str(out),
                "--figures",
                str(tmp_path / "fig2"),
            ],
        )
        assert res2.exit_code == 0, res2.output
        assert (tmp_path / "fig2" / "recall_at_n.png").is_file()


def test_cli_eval_from_published_pickles_matches_splits(
    trained: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    """The same model on the same sets, read from our JSON and from exported pickles."""
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.data import splits as sp

    root, splits, run = trained
    sp.export_pickles(sp.load_splits(splits), tmp_path / "pk")
    (tmp_path / "pk" / "training_queries_baseline.pickle").unlink(missing_ok=True)
    reps = []
    for src in (["--splits", str(splits)], ["--pickles", str(tmp_path / "pk")]):
        out = tmp_path / f"{src[0][2:]}.json"
        res = CliRunner().invoke(
            app,
            [
                "-q",
                "eval",
                "--checkpoint",
                str(run / "model"),
                "--root",
                str(root),
                *src,
                "-o",
                str(out),
                "--no-progress",
            ],
        )
        assert res.exit_code == 0, res.output
        reps.append(evaluate.read_report(out))
    assert reps[0]["recall_at_n"] == pytest.approx(reps[1]["recall_at_n"])
    assert reps[0]["recall_at_1pct"] == pytest.approx(reps[1]["recall_at_1pct"])


def test_cli_eval_summary_names_what_was_evaluated(
    trained: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    """The summary line names the model directory and its architecture (or "baseline"), not
    the folder the command was pointed at: `-m RUN` evaluates RUN/model."""
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    root, splits, run = trained
    data = ["--root", str(root), "--splits", str(splits), "--no-progress"]
    model = f"{run / 'model'} (pointnetvlad)"  # the run's final model: a compact PN_VLAD
    for what, label in (
        (["--checkpoint", str(run)], model),
        (["-m", str(run)], model),
        (["--model", str(run / "model")], model),
        (["--baseline"], "baseline"),
    ):
        res = CliRunner().invoke(app, ["-q", "eval", *what, *data])
        assert res.exit_code == 0, res.output
        first = res.stdout.splitlines()[0]
        pattern = rf"{re.escape(label)}: recall@1 [\d.]+ %, recall@1% [\d.]+ % over 6 run pairs"
        assert re.fullmatch(pattern + r" \(\d+ queries\)", first), first


def test_cli_eval_errors_exit_2(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    res = CliRunner().invoke(app, ["eval", "--root", str(tmp_path)])
    assert res.exit_code == 2 and "--model" in res.output
    res = CliRunner().invoke(
        app, ["eval", "--checkpoint", str(tmp_path / "none"), "--root", str(tmp_path)]
    )
    assert res.exit_code == 2
    # a training run that has not written its final model yet: named as such
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    res = CliRunner().invoke(app, ["eval", "-m", str(tmp_path / "run"), "--root", str(tmp_path)])
    assert res.exit_code == 2 and "has not finished" in res.output


def _has_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def test_cli_eval_num_points_overrides_the_models(
    trained: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    root, splits, run = trained
    common = ["-q", "eval", "--checkpoint", str(run), "--root", str(root)]
    common += ["--splits", str(splits), "--no-progress"]
    reports = {}
    for n in (None, 4096):
        out = tmp_path / f"rep{n}.json"
        extra = [] if n is None else ["--num-points", str(n)]
        res = CliRunner().invoke(app, [*common, "-o", str(out), *extra])
        assert res.exit_code == 0, res.output
        reports[n] = evaluate.read_report(out)
    model_points = reports[None]["num_points"]
    assert model_points != 4096  # the tiny test model trains on fewer points
    assert reports[4096]["num_points"] == 4096
    res = CliRunner().invoke(app, [*common, "--num-points", "0"])
    assert res.exit_code == 2 and "--num-points" in res.output


def test_summary_lines_and_figures_of_a_two_area_report(tmp_path: Path) -> None:
    def figures(r1: float, pct: float, pairs: int) -> dict:
        return {"recall_at_1": r1, "recall_at_1pct": pct, "n_pairs": pairs}

    runs, _ = hand_case(tmp_path / "data")
    rep = evaluate.evaluate_runs(mean_embedder, runs, 64, progress=False, joint=True)
    rep["per_area"] = {"a": {**rep["per_area"]["line"]}, "b": {**rep["per_area"]["line"]}}
    rep.update(figures(50.0, 62.5, 12), n_queries_evaluated=120)
    rep["per_area"]["b"].update(figures(25.0, 37.125, 6))
    rep["joint"].update(figures(12.5, 100.0, 0), n_queries=30)
    a = rep["per_area"]["a"]
    assert evaluate.summary_lines("m (pointnetvlad)", rep) == [
        "m (pointnetvlad): recall@1 50.00 %, recall@1% 62.50 % over 12 run pairs (120 queries)",
        f"  a: recall@1 {a['recall_at_1']:.2f} %, recall@1% {a['recall_at_1pct']:.2f} %",
        "  b: recall@1 25.00 %, recall@1% 37.12 %",
        "  joint database: recall@1 12.50 %, recall@1% 100.00 %",
    ]
    del rep["joint"]
    rep["per_area"].pop("b")
    assert len(evaluate.summary_lines("x", rep)) == 1  # one area: no per-area lines
    pytest.importorskip("matplotlib")
    rep["per_area"]["b"] = rep["per_area"]["a"]
    evaluate.write_figures("x", rep, tmp_path / "fig", [("other", rep)])
    names = sorted(p.name for p in (tmp_path / "fig").iterdir())
    assert names == ["query_map.png", "recall_at_n.png", "recall_at_n_by_area.png"]


def test_cli_eval_dtype(trained: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """--dtype: a bad value and bfloat16 on the baseline exit 2 naming the flag; bfloat16 runs
    where the CPU has it natively (the report says so, and the recall stays near float32's)
    and is refused, naming the dtype, where it has not."""
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.models.inference import bf16_supported

    root, splits, run = trained
    common = ["-q", "eval", "--root", str(root), "--splits", str(splits), "--no-progress"]
    res = CliRunner().invoke(app, [*common, "--checkpoint", str(run), "--dtype", "float16"])
    assert res.exit_code == 2 and "--dtype" in res.output and "float16" in res.output
    res = CliRunner().invoke(app, [*common, "--baseline", "--dtype", "bfloat16"])
    assert res.exit_code == 2 and "--dtype" in res.output
    reports = {}
    for dtype in ("float32", "bfloat16"):
        out = tmp_path / f"{dtype}.json"
        args = [*common, "--checkpoint", str(run), "--dtype", dtype, "-o", str(out)]
        res = CliRunner().invoke(app, args)
        if dtype == "bfloat16" and not bf16_supported():
            assert res.exit_code == 2 and "bfloat16" in res.output and not out.exists()
            return
        assert res.exit_code == 0, res.output
        reports[dtype] = evaluate.read_report(out)
        assert reports[dtype]["encoder"]["dtype"] == dtype
    # 30 submaps a database: a few swapped near-ties move recall@1 by a few per cent at most
    assert abs(reports["bfloat16"]["recall_at_1"] - reports["float32"]["recall_at_1"]) <= 10


def test_exact_search_over_a_map_of_turns_counts_each_entry_once() -> None:
    """Database rows of T headings' descriptors side by side: a row's distance is its nearest
    heading's, each row once in the ranking (first_rows), as the bundles search."""
    from pnvlad_service.evaluation.evaluate import exact_search, first_rows

    rng = np.random.default_rng(0)
    db = rng.normal(size=(6, 4, 8)).astype(np.float32)  # 6 entries x 4 headings x D = 8
    q = db[[4, 1], [3, 0]] + 1e-4  # entry 4 at its 4th heading, entry 1 at its 1st
    nn = exact_search(db.reshape(6, 32), q, 6)
    assert nn[:, 0].tolist() == [4, 1]
    assert all(sorted(row.tolist()) == list(range(6)) for row in nn)
    # By brute force: each entry's best heading, then sorted.
    d = np.linalg.norm(db[None] - q[:, None, None], axis=-1).min(axis=2)
    np.testing.assert_array_equal(nn, np.argsort(d, axis=1, kind="stable"))
    assert first_rows(np.array([[3, 3, 1, -1, 2]]), 4).tolist() == [[3, 1, 2, -1]]


def test_a_smoothed_map_is_each_runs_database_blended_along_the_run(tmp_path: Path) -> None:
    from pnvlad_service.index.smoothing import Smoothing

    runs, desc = hand_case(tmp_path)
    sm = Smoothing(25.0, 0.5)
    rep = evaluate.evaluate_runs(mean_embedder, runs, 64, progress=False, smoothing=sm)
    assert rep["map_smoothing"] == {"radius_m": 25.0, "weight": 0.5}
    # by hand: each database entry plus half the mean of its run's entries 20 m either side,
    # unit length; the queries as they are
    _, raw_db, q = evaluate.embed_runs(mean_embedder, runs, 64, 1, False)
    db = []
    for r in range(3):
        raw = raw_db[r].astype(np.float64)
        np.testing.assert_allclose(raw, [desc[(r, k)] for k in range(10)], atol=1e-6)
        out = []
        for k in range(10):
            near = [j for j in (k - 1, k + 1) if 0 <= j < 10]
            v = raw[k] + 0.5 * raw[near].mean(axis=0)
            out.append(v / np.linalg.norm(v))
        db.append(np.array(out, dtype=np.float32))
    _, got_db, got_q = evaluate.embed_runs(mean_embedder, runs, 64, 1, False, smoothing=sm)
    for r in range(3):
        np.testing.assert_allclose(got_db[r], db[r], atol=1e-6)
        np.testing.assert_array_equal(got_q[r], q[r])
    assert "map smoothed (25 m, weight 0.5)" in evaluate.summary_lines("m", rep)[0]

    # with unit descriptors, a vanishing weight is the plain map
    def unit_embedder(points: np.ndarray) -> np.ndarray:
        d = mean_embedder(points) + np.array([0.0, 0.0, 1.0], dtype=np.float32)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    plain = evaluate.evaluate_runs(unit_embedder, runs, 64, progress=False)
    faint = evaluate.evaluate_runs(
        unit_embedder, runs, 64, progress=False, smoothing=Smoothing(25.0, 1e-9)
    )
    assert plain["map_smoothing"] is None
    assert faint["recall_at_n"] == plain["recall_at_n"]


def test_cli_eval_smoothed_map(trained: tuple[Path, Path, Path], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    root, splits, run = trained
    base = ["-q", "eval", "-m", str(run), "--root", str(root), "--splits", str(splits)]
    out = tmp_path / "rep.json"
    res = CliRunner().invoke(
        app, [*base, "--smooth", "25", "--smooth-weight", "0.7", "-o", str(out), "--no-progress"]
    )
    assert res.exit_code == 0, res.output
    assert evaluate.read_report(out)["map_smoothing"] == {"radius_m": 25.0, "weight": 0.7}
    assert "map smoothed (25 m, weight 0.7)" in res.output
    bad = CliRunner().invoke(app, [*base, "--smooth-weight", "0.7", "--no-progress"])
    assert bad.exit_code == 2 and "--smooth-weight" in bad.output
