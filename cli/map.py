"""`pnvlad map`: a map's runs made into one map that agrees with itself.

Library imports happen inside the commands so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli.common import model_option, user_errors

app = typer.Typer(
    rich_markup_mode="markdown",
    help="Work on a map's runs as one map: align them (pose graph of odometry, verified loop "
    "closures and GNSS/INS fixes), so that every run puts each place where the others do.",
    no_args_is_help=True,
)

_GNSS = "GNSS/INS error model"
_CLOSURES = "Closures"


_ROOT = typer.Argument(..., help="The benchmark tree whose runs to align (read only).")
_OUT = typer.Option(
    None, "--out", "-o", help="The aligned tree to write (default: ROOT-aligned beside ROOT)."
)
_MODEL = model_option(
    None,
    help="Encoder whose retrieval proposes closure candidates besides the recorded poses' "
    "nearby entries (without one, only the recorded poses propose them).",
)
_KIND = typer.Option(
    "keyframe", "--kind", help="The entries that are the graph's nodes: keyframe or test."
)
_RADIUS = typer.Option(
    10.0,
    "--radius",
    help="Nearby candidates: other runs' entries within this (m) of a query's recorded position.",
    rich_help_panel=_CLOSURES,
)
_EVERY = typer.Option(
    4, "--every", help="One query node every this many nodes of a run.", rich_help_panel=_CLOSURES
)
_GATE = typer.Option(
    8.5,
    "--gate",
    help="A verified closure farther than this (m) from the recorded poses is rejected.",
    rich_help_panel=_CLOSURES,
)
_POSITION_STD = typer.Option(
    1.5,
    "--position-std",
    help="Horizontal std of the recorded positions' error (m).",
    rich_help_panel=_GNSS,
)
_HEADING_STD = typer.Option(
    0.8,
    "--heading-std",
    help="Std of the recorded heading's error (degrees).",
    rich_help_panel=_GNSS,
)
_CORRELATION = typer.Option(
    60.0,
    "--correlation",
    help="Distance driven over which that error decorrelates (m).",
    rich_help_panel=_GNSS,
)
_SWEEP_HZ = typer.Option(
    None,
    "--sweep-hz",
    min=0.0,
    help="Sweeps a second of the spinning sensors whose drivers do not de-skew (e.g. 10): "
    "each keyframe's scan is de-skewed by the motion its recording gave it (the sidecar's "
    "heading, speed and yaw rate), or where it has none by the motion a first odometry pass "
    "measures. 0: no scan is de-skewed. Default: a synthetic tree's runs at their sensor's "
    "rate where it does not de-skew (synth.json), a recording's not at all.",
)
_ALONE = typer.Option(
    False,
    "--allow-alone",
    help="Keep a run that shares no verified place with the others on its own fixes instead "
    "of refusing the map.",
)


@app.command()
def align(
    root: Path = _ROOT,
    out: Path = _OUT,
    model: Path = _MODEL,
    kind: str = _KIND,
    radius_m: float = _RADIUS,
    every: int = _EVERY,
    gate_m: float = _GATE,
    position_std_m: float = _POSITION_STD,
    heading_std_deg: float = _HEADING_STD,
    correlation_m: float = _CORRELATION,
    allow_alone: bool = _ALONE,
    sweep_hz: float | None = _SWEEP_HZ,
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing OUT."),
) -> None:
    """Align the runs of a map into one consistent map and write it as a new tree.

    Odometry edges register each entry onto the one before it; closure candidates (retrieval
    with --model, and other runs' entries near the recorded pose) are verified by the
    service's own verification; the recorded GNSS/INS poses enter as a correlated walk of the
    given std and correlation length; GTSAM solves the graph under robust kernels. The tree at
    ROOT is only read: OUT gets every run re-laid by the solved poses (same layout, so `pnvlad
    index build -r OUT` uses it), each run's aligned_poses.csv, align_report.json and
    align.png. A run prepared from position fixes only (`pnvlad data prepare --fix-topic ...
    --odometry kiss-icp`, its fixes.csv beside it) is held to its fixes, with KISS-ICP's step
    where a registration fails.

    Example: pnvlad map align city/ -o city-aligned/ -m runs/bev/model
    """
    from pnvlad_service.mapping.align import AlignConfig, align_map
    from pnvlad_service.mapping.candidates import CandidateConfig
    from pnvlad_service.mapping.edges import EdgeConfig
    from pnvlad_service.mapping.graph import GnssModel, GraphConfig

    if kind not in ("keyframe", "test"):
        raise typer.BadParameter(f"{kind!r} is not one of keyframe, test", param_hint="--kind")
    target = out if out is not None else root.with_name(root.name + "-aligned")
    config = AlignConfig(
        kind=kind,  # type: ignore[arg-type]
        allow_alone=allow_alone,
        sweep_hz=sweep_hz,
        candidates=CandidateConfig(every=every, radius_m=radius_m),
        edges=EdgeConfig(gate_m=gate_m),
        graph=GraphConfig(
            gnss=GnssModel(
                position_std_m=position_std_m,
                heading_std_deg=heading_std_deg,
                correlation_m=correlation_m,
            )
        ),
    )
    with user_errors():
        result = align_map(root, target, model=model, config=config, overwrite=overwrite)
    rep = result.report
    closures = rep["closures"]
    typer.echo(
        f"aligned {len(rep['runs'])} runs ({rep['nodes']} nodes): "
        f"{rep['odometry']['accepted']}/{rep['odometry']['steps']} odometry steps, "
        f"{closures['accepted']} closures accepted, {closures['rejected']} rejected "
        f"-> {target}"
    )
    for run in rep["corrections"]:
        moved = run["moved_m"]
        typer.echo(
            f"  {run['run']}: moved median {moved['median']:.2f} m, max {moved['max']:.2f} m"
        )
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in result.seconds.items())
    typer.echo(f"stages: {stages}")
