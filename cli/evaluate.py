"""`pnvlad eval`: recall of a trained model (or the baseline) on a benchmark's evaluation sets."""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli.common import user_errors

_WHAT = "What to evaluate"
_DATA = "Data"
_OUT = "Output"


def evaluate(
    checkpoint: Path = typer.Option(
        None,
        "--checkpoint",
        help="A model directory (model.json + model.safetensors), a training checkpoint, or a "
        "training run directory (its model/ is used).",
        rich_help_panel=_WHAT,
    ),
    baseline: bool = typer.Option(
        False,
        "--baseline",
        help="Evaluate the training-free baseline descriptor instead.",
        rich_help_panel=_WHAT,
    ),
    root: Path = typer.Option(None, "--root", help="Benchmark tree root.", rich_help_panel=_DATA),
    splits: Path = typer.Option(
        None, "--splits", help="Splits JSON (default: built from the tree).", rich_help_panel=_DATA
    ),
    pickles: Path = typer.Option(
        None,
        "--pickles",
        help="Folder (or file) of the published evaluation pickles instead of --splits.",
        rich_help_panel=_DATA,
    ),
    sets: list[str] = typer.Option(
        None,
        "--set",
        help="Only this evaluation set (repeatable; default: all).",
        rich_help_panel=_DATA,
    ),
    joint: bool = typer.Option(
        False,
        "--joint",
        help="Also evaluate one database of every run and area together.",
        rich_help_panel=_WHAT,
    ),
    out: Path = typer.Option(
        None,
        "--out",
        "-o",
        help="JSON report path (default: print a summary only).",
        rich_help_panel=_OUT,
    ),
    figures: Path = typer.Option(
        None,
        "--figures",
        help="Folder for PNG figures: recall@N curves and the query map (needs the plot extra).",
        rich_help_panel=_OUT,
    ),
    plot: list[Path] = typer.Option(
        None,
        "--plot",
        help="Existing report(s) to draw on the recall@N figure (repeatable); without "
        "--checkpoint/--baseline only plots them into --figures.",
        rich_help_panel=_OUT,
    ),
    num_points: int = typer.Option(
        None,
        "--num-points",
        help="Points of each submap fed to the encoder (default: the model's num_points). "
        "A model trained on fewer points can be evaluated on all 4096, as the index and the "
        "server embed them.",
        rich_help_panel=_WHAT,
    ),
    device: str = typer.Option(None, "--device", help="cpu | cuda (default: cpu)."),
    workers: int = typer.Option(4, "--workers", help="Threads reading submaps."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Evaluate place recognition as the PointNetVLAD benchmark does.

    Embeds every unique submap of each run once, searches each query run against every other
    run's database with FAISS and reports recall@1..25 and recall@1% averaged over all ordered
    run pairs (queries without ground truth skipped), per evaluation set and overall, plus
    recall@1 against the distance threshold and, with --joint, one database of all runs.

    Examples:

      pnvlad eval --checkpoint runs/a --root city/ --splits city/splits.json -o a.json

      pnvlad eval --baseline --root benchmark_datasets/ --pickles pickles/ -o b.json --figures f/

      pnvlad eval --plot a.json --plot base.json --figures figs/
    """
    with user_errors():
        from pnvlad_service.errors import InputError
        from pnvlad_service.evaluation import evaluate as ev

        others = [(p.stem, ev.read_report(p)) for p in (plot or [])]
        if checkpoint is None and not baseline:
            if not others:
                raise InputError("give --checkpoint, --baseline or --plot REPORT", "--checkpoint")
            if figures is None:
                raise InputError("--plot needs --figures, the folder for the PNGs", "--figures")
            path = ev.plot_recall_curves(others, figures / "recall_at_n.png")
            typer.echo(f"wrote {path}")
            return
        if checkpoint is not None and baseline:
            raise InputError("give --checkpoint or --baseline, not both", "--baseline")
        from pnvlad_service.data.dataset import load_eval_runs

        runs = load_eval_runs(root, splits, pickles, sets)
        if baseline:
            embed, model_points, info = ev.baseline_embedder()
            label = "baseline"
        else:
            ckpt = (
                checkpoint / "model"
                if (checkpoint / "model" / "model.json").is_file()
                else checkpoint
            )
            embed, model_points, info = ev.checkpoint_embedder(ckpt, device)
            label = checkpoint.name
        if num_points is None:
            num_points = model_points
        elif num_points < 1:
            raise InputError(f"must be >= 1, got {num_points}", "--num-points")
        rep = ev.evaluate_runs(
            embed,
            runs,
            num_points,
            joint=joint,
            workers=workers,
            progress=progress,
            encoder_info=info,
        )
        if out is not None:
            ev.write_report(rep, out)
        typer.echo(
            f"{label}: {_fmt(rep)} over {rep['n_pairs']} run pairs "
            f"({rep['n_queries_evaluated']} queries)"
        )
        for area, a in rep["per_area"].items():
            if len(rep["per_area"]) > 1:
                typer.echo(f"  {area}: {_fmt(a)}")
        if "joint" in rep and rep["joint"].get("n_queries"):
            j = rep["joint"]
            typer.echo(f"  joint database: {_fmt(j)}")
        if figures is not None:
            ev.plot_recall_curves([(label, rep), *others], figures / "recall_at_n.png")
            ev.plot_query_map(rep, figures / "query_map.png")
            areas = [(a, r) for a, r in rep["per_area"].items() if r.get("n_pairs")]
            if len(areas) > 1:
                ev.plot_recall_curves(areas, figures / "recall_at_n_by_area.png", title=label)
            typer.echo(f"figures in {figures}")


def _fmt(r: dict) -> str:
    return f"recall@1 {r['recall_at_1']:.2f} %, recall@1% {r['recall_at_1pct']:.2f} %"
