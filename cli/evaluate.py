"""`pnvlad eval`: recall of a trained model (or the baseline) on a benchmark's evaluation sets."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli.common import (
    model_option,
    pickles_option,
    progress_option,
    root_option,
    smooth_option,
    smooth_weight_option,
    splits_option,
    user_errors,
)

_WHAT = "What to evaluate"
_DATA = "Data"
_OUT = "Output"

_MODEL = model_option(panel=_WHAT)
_BASELINE = typer.Option(
    False,
    "--baseline",
    help="Evaluate the training-free baseline descriptor instead.",
    rich_help_panel=_WHAT,
)
_PICKLES = pickles_option(
    "Folder (or file) of the published evaluation pickles instead of --splits.", _DATA
)
_SETS = typer.Option(
    None,
    "--set",
    help="Only this evaluation set (repeatable; default: all).",
    rich_help_panel=_DATA,
)
_JOINT = typer.Option(
    False,
    "--joint",
    help="Also evaluate one database of every run and area together.",
    rich_help_panel=_WHAT,
)
_VERIFY = "Verification (re-ranking)"
_RERANK = typer.Option(
    None,
    "--rerank",
    help="Register each query's top K candidates and re-rank them by score: reports recall "
    "before and after, the metric success rate against the true poses, and the precision and "
    "recall of 'verified' (needs the tree's frame sidecars).",
    rich_help_panel=_VERIFY,
)
_THRESHOLD = typer.Option(
    None,
    "--verify-threshold",
    help="Score a best match needs to be verified (default: chosen on the training layout).",
    rich_help_panel=_VERIFY,
)
_CAL_QUERIES = typer.Option(
    None,
    "--calibration-queries",
    help="Training-layout queries a run that choose the threshold (default: 150, which "
    "keeps the 99.5 % precision rule steady; see docs/VERIFY.md).",
    rich_help_panel=_VERIFY,
)
_OFF_MAP = typer.Option(
    None,
    "--off-map-share",
    help="Share of queries (0-1) the threshold plans for whose place is not among their "
    "candidates; training-layout queries verified against submaps over 50 m away stand in "
    "for them (default: 0.05; 0: none; docs/VERIFY.md).",
    rich_help_panel=_VERIFY,
)
_SAVE_THRESHOLD = typer.Option(
    False,
    "--save-threshold",
    help="Write the threshold chosen on the training layout to MODEL/verification.json, "
    "where pnvlad serve and pnvlad localize --index take it from (for these weights only).",
    rich_help_panel=_VERIFY,
)
_OUT_OPT = typer.Option(
    None,
    "--out",
    "-o",
    help="JSON report path (default: print a summary only).",
    rich_help_panel=_OUT,
)
_FIGURES = typer.Option(
    None,
    "--figures",
    help="Folder for PNG figures: recall@N curves and the query map (needs the plot extra).",
    rich_help_panel=_OUT,
)
_PLOT = typer.Option(
    None,
    "--plot",
    help="Existing report(s) to draw on the recall@N figure (repeatable); without "
    "--model/--baseline only plots them into --figures.",
    rich_help_panel=_OUT,
)
_QUERIES = typer.Option(
    "submaps",
    "--queries",
    help="What the queries are: 'submaps' (the benchmark's, accumulated offline), 'scans' "
    "(the raw scan at each query submap's place, run through the map's filter G, in the "
    "sensor's frame: what a robot sends; needs raw_scans/ in the runs) or 'windows' (the "
    "scans of the last --window-m of driving before each place, laid with --window-poses: a "
    "pnvlad synth tree's runs are cast again for them). The map is the one --splits "
    "describes: splits.json the 20 m submaps, splits_keyframes.json the keyframes.",
    rich_help_panel=_DATA,
)
_WINDOW_POSES = typer.Option(
    "recorded",
    "--window-poses",
    help="With --queries windows: 'recorded' (the run's GNSS/INS poses, as a bag's pose topic: "
    "the window in the map's axes) or 'odometry' (KISS-ICP from the scans alone, extra "
    "'odometry': the window in the newest scan's axes).",
    rich_help_panel=_DATA,
)
_WINDOW_M = typer.Option(
    20.0, "--window-m", help="With --queries windows: metres of driving a window holds.",
    rich_help_panel=_DATA,
)  # fmt: skip
_NUM_POINTS = typer.Option(
    None,
    "--num-points",
    help="Points of each submap fed to the encoder (default: the model's num_points). "
    "A model trained on fewer points can be evaluated on all 4096, as the index and the "
    "server embed them.",
    rich_help_panel=_WHAT,
)


def evaluate(
    model: Path = _MODEL,
    baseline: bool = _BASELINE,
    root: Path = root_option(panel=_DATA),
    splits: Path = splits_option(panel=_DATA),
    pickles: Path = _PICKLES,
    sets: list[str] = _SETS,
    queries: str = _QUERIES,
    window_poses: str = _WINDOW_POSES,
    window_m: float = _WINDOW_M,
    joint: bool = _JOINT,
    out: Path = _OUT_OPT,
    figures: Path = _FIGURES,
    plot: list[Path] = _PLOT,
    num_points: int = _NUM_POINTS,
    smooth: float | None = smooth_option(panel=_WHAT),
    smooth_weight: float | None = smooth_weight_option(panel=_WHAT),
    rerank: int = _RERANK,
    verify_threshold: float = _THRESHOLD,
    calibration_queries: int | None = _CAL_QUERIES,
    off_map_share: float | None = _OFF_MAP,
    save_threshold: bool = _SAVE_THRESHOLD,
    device: str = typer.Option(None, "--device", help="cpu | cuda (default: cpu)."),
    dtype: str = typer.Option(
        "float32",
        "--dtype",
        help="Precision of the encoder's products: float32, or bfloat16 on a CPU that has it "
        "natively (AVX512-BF16 or AMX; refused elsewhere): the recall it would serve at.",
    ),
    workers: int = typer.Option(4, "--workers", help="Threads reading submaps."),
    progress: bool = progress_option(),
) -> None:
    """Evaluate place recognition as the PointNetVLAD benchmark does.

    Embeds every unique submap of each run once, searches each query run against every other
    run's database with FAISS and reports recall@1..25 and recall@1% averaged over all ordered
    run pairs (queries without ground truth skipped), per evaluation set and overall, plus
    recall@1 against the distance threshold and, with --joint, one database of all runs.

    Examples:

      pnvlad eval -m runs/a --root city/ --splits city/splits.json -o a.json

      pnvlad eval --baseline --root benchmark_datasets/ --pickles pickles/ -o b.json --figures f/

      pnvlad eval --plot a.json --plot base.json --figures figs/

      pnvlad eval -m runs/a --root city/ --splits city/splits.json --rerank 10 --figures f/

      pnvlad eval -m runs/a --root city/ --splits city/splits.json --rerank 10 --save-threshold

      pnvlad eval -m runs/s --root city/ --splits city/splits_keyframes.json --queries scans

      pnvlad eval -m runs/a --root city/ --splits city/splits.json --smooth 25
    """
    if rerank is not None:
        # Before torch, faiss and small_gicp load their OpenMP runtimes: registration's two
        # threads otherwise spin at each barrier and stall for scheduler slices whenever
        # another process holds a core (8+ min against 5 beside a training run); at batch 32
        # the embedding is as fast either way (docs/VERIFY.md). A value the user set is kept.
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    with user_errors(), contextlib.ExitStack() as stack:
        from pnvlad_service.evaluation import evaluate as ev
        from pnvlad_service.index.smoothing import Smoothing

        others = [(p.stem, ev.read_report(p)) for p in (plot or [])]
        if model is None and not baseline:
            _plot_only(others, figures)
            return
        _check_options(
            model=model,
            baseline=baseline,
            root=root,
            pickles=pickles,
            queries=queries,
            num_points=num_points,
            rerank=rerank,
            verify_threshold=verify_threshold,
            off_map_share=off_map_share,
            save_threshold=save_threshold,
            dtype=dtype,
        )
        smoothing = Smoothing.of(smooth, smooth_weight)
        enc = ev.baseline_encoder() if baseline else ev.model_encoder(model, device, dtype)
        points = enc.num_points if num_points is None else num_points
        scan_set, runs = _query_runs(
            queries,
            root,
            splits,
            pickles,
            sets,
            stack.enter_context,
            progress,
            (window_poses, window_m),
        )
        rep, db_desc, q_desc = _report(enc, runs, points, workers, progress, joint, smoothing)
        if scan_set is not None:
            from pnvlad_service.evaluation import scan_queries

            rep.update(scan_queries.scan_report(scan_set, runs, db_desc, q_desc, points))
        if rerank is not None:
            from pnvlad_service.data.dataset import load_splits_any
            from pnvlad_service.evaluation import scan_queries
            from pnvlad_service.evaluation.rerank import evaluate_rerank

            rep["rerank"] = evaluate_rerank(
                enc.embed,
                points,
                runs,
                (db_desc, q_desc),
                root,
                load_splits_any(root, splits, pickles).training,
                candidates=rerank,
                threshold=verify_threshold,
                calibration_queries=calibration_queries,
                off_map_share=off_map_share,
                workers=workers,
                progress=progress,
                query_frames=None
                if scan_set is None
                else scan_queries.query_frames(scan_set, runs),
                smoothing=smoothing,
            )
        if save_threshold:
            _save_threshold(rep, enc.info, rerank)
        _show(enc.label, rep, out, figures, others)


def _report(
    enc: Any, runs: list, points: int, workers: int, progress: bool, joint: bool, smoothing: Any
) -> tuple[dict[str, Any], list, list]:
    """(the recall report, each run's database and query descriptors): every unique submap
    embedded once, the databases smoothed along their runs with ``smoothing``."""
    from pnvlad_service.evaluation import evaluate as ev

    n_unique, db_desc, q_desc = ev.embed_runs(
        enc.embed, runs, points, workers, progress, smoothing=smoothing
    )
    rep = ev.evaluate_embedded(
        runs,
        db_desc,
        q_desc,
        joint=joint,
        encoder_info=enc.info,
        num_points=points,
        n_unique=n_unique,
        smoothing=smoothing,
    )
    return rep, db_desc, q_desc


def _plot_only(others: list, figures: Path | None) -> None:
    """``--plot`` without a model: the reports' recall@N curves drawn into ``--figures``."""
    from pnvlad_service.errors import InputError
    from pnvlad_service.evaluation import evaluate as ev

    if not others:
        raise InputError("give --model (-m), --baseline or --plot REPORT", "--model")
    if figures is None:
        raise InputError("--plot needs --figures, the folder for the PNGs", "--figures")
    typer.echo(f"wrote {ev.plot_recall_curves(others, figures / 'recall_at_n.png')}")


def _check_options(
    *,
    model: Path | None,
    baseline: bool,
    root: Path | None,
    pickles: Path | None,
    queries: str,
    num_points: int | None,
    rerank: int | None,
    verify_threshold: float | None,
    off_map_share: float | None,
    save_threshold: bool,
    dtype: str,
) -> None:
    """Every option checked against the others before a model is loaded: an ``InputError``
    naming the option at fault."""
    from pnvlad_service.errors import InputError

    if model is not None and baseline:
        raise InputError("give --model or --baseline, not both", "--baseline")
    if num_points is not None and num_points < 1:
        raise InputError(f"must be >= 1, got {num_points}", "--num-points")
    if rerank is not None and not 1 <= rerank <= 100:
        raise InputError(f"must be 1..100, got {rerank}", "--rerank")
    if rerank is not None and root is None:
        raise InputError("re-ranking reads the tree's frame sidecars: give --root", "--root")
    if off_map_share is not None and not 0.0 <= off_map_share < 1.0:
        raise InputError(f"must be in [0, 1), got {off_map_share}", "--off-map-share")
    if rerank is None and verify_threshold is not None:
        raise InputError("applies with --rerank only", "--verify-threshold")
    if save_threshold and (rerank is None or model is None or verify_threshold is not None):
        raise InputError(
            "needs --model and --rerank K, and a threshold chosen here (no --verify-threshold)",
            "--save-threshold",
        )
    if dtype not in ("float32", "bfloat16"):
        raise InputError(f"must be float32 or bfloat16, got {dtype!r}", "--dtype")
    if baseline and dtype != "float32":
        raise InputError("the baseline has no encoder to run in bfloat16", "--dtype")
    if queries not in ("submaps", "scans", "windows"):
        raise InputError(f"must be submaps, scans or windows, got {queries!r}", "--queries")
    if queries != "submaps" and (root is None or pickles is not None):
        raise InputError(f"{queries} queries are read from the tree: give --root", "--queries")


def _query_runs(
    queries: str,
    root: Path | None,
    splits: Path | None,
    pickles: Path | None,
    sets: list[str] | None,
    enter: Any,
    progress: bool,
    window: tuple[str, float] = ("recorded", 20.0),
) -> tuple[Any, list]:
    """(the scan query set or ``None``, the evaluation runs): with ``--queries scans`` the raw
    scans, with ``windows`` the windows of scans before them (``window``: their poses and
    metres), run through G into a temporary folder (``enter`` keeps it for the command's
    life), else the tree's or the pickles' submaps. At least two runs."""
    from pnvlad_service.data.dataset import load_eval_runs, load_splits_any
    from pnvlad_service.errors import InputError

    scan_set = None
    if queries != "submaps":
        from pnvlad_service.evaluation import scan_queries

        scan_set = scan_queries.scan_query_set(root, load_splits_any(root, splits), sets)
        tmp = Path(enter(tempfile.TemporaryDirectory()))
        if queries == "windows":
            from pnvlad_service.synth.windows import window_queries

            poses, metres = window
            scan_set = window_queries(
                scan_set, root, tmp / "windows", poses=poses, window_m=metres, progress=progress
            )
        runs = scan_queries.preprocess_queries(scan_set, tmp / "g", progress=progress)
    else:
        runs = load_eval_runs(root, splits, pickles, sets)
    if len(runs) < 2:
        raise InputError(f"need at least 2 runs to evaluate, got {len(runs)}", "evaluation set")
    return scan_set, runs


def _save_threshold(rep: dict[str, Any], info: dict[str, Any], rerank: int) -> None:
    """``--save-threshold``: the threshold chosen here written beside the model's weights."""
    from pnvlad_service.localization.query import calibration as cal

    # The directory and weights the encoder evaluated (not hashed again here).
    record = cal.Calibration.from_report(
        rep["rerank"]["calibration"], info["weights_sha256"], rerank
    )
    where = cal.write_calibration(info["path"], record)
    typer.echo(f"verification threshold {record.threshold:.2f} written to {where}")


def _show(
    label: str, rep: dict[str, Any], out: Path | None, figures: Path | None, others: list
) -> None:
    """The report written to ``--out``, its summary printed, its figures drawn."""
    from pnvlad_service.evaluation import evaluate as ev
    from pnvlad_service.evaluation import rerank_report

    if out is not None:
        ev.write_report(rep, out)
    for line in ev.summary_lines(label, rep):
        typer.echo(line)
    if "rerank" in rep:
        for line in rerank_report.summary_lines(rep["rerank"]):
            typer.echo(line)
    if figures is not None:
        ev.write_figures(label, rep, figures, others)
        if "rerank" in rep:
            rerank_report.write_figures(rep["rerank"], figures)
        typer.echo(f"figures in {figures}")
