"""`pnvlad synth`: the built-in synthetic LiDAR city benchmark."""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli.common import progress_option, user_errors

#: What --preset offers, each with its size and time.
PRESETS_HELP = (
    "tiny (tests, seconds), demo (README, ~600 submaps, under 2 min), benchmark "
    "(3 districts x 5 runs recorded with four real sensors' layouts, quality figures, under "
    "30 min), benchmark_v1 (the first benchmark: one perfect sensor, no street "
    "detail), pushbroom_tiny / pushbroom_demo (the paper's Oxford sensor: a SICK "
    "LMS-151 push-broom mounted as the RobotCar's lms_front, Oxford-style submaps), or "
    "oxford (the paper's Oxford: an old town over the RobotCar's coordinates, 8 runs of "
    "a 5 km route, partial runs, written as oxford/RUN/pointcloud_20m/ and "
    "pointcloud_20m_10overlap/ with their CSVs; about 10 min of CPU, 5-6 min on 2 idle "
    "cores) / oxford_tiny (tests, seconds)."
)


def synth(
    out: Path = typer.Option(..., "--out", "-o", help="Tree root to create."),
    preset: str = typer.Option(
        "demo",
        "--preset",
        help=PRESETS_HELP,
    ),
    seed: int = typer.Option(0, "--seed", "-s", help="Seed of the city and of every run."),
    workers: int = typer.Option(
        0, "--workers", "-w", help="Processes generating runs in parallel (0: one per core)."
    ),
    trajectories: Path | None = typer.Option(
        None,
        "--trajectories",
        help="Folder of CSVs (northing,easting; AREA_K.csv or K.csv for run K) to drive "
        "instead of the generated route.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing tree."),
    preview: Path | None = typer.Option(
        None,
        "--preview",
        help="Also render PNG previews (map with trajectories, submaps before and after G) "
        "into this folder. Needs the 'plot' extra.",
    ),
    refresh_truth: bool = typer.Option(
        False,
        "--refresh-truth",
        help="Do not generate: recompute the true poses and the keyframes' motion in the frame "
        "sidecars of the existing tree OUT (made by an older pnvlad, whose truth was the centre "
        "scan's and whose keyframes had no motion) from its synth.json, in seconds. Give "
        "--trajectories if the tree was made with them.",
    ),
    progress: bool = progress_option(),
) -> None:
    """Generate a synthetic LiDAR benchmark in the public PointNetVLAD layout.

    A seeded city (business, residential and campus districts) is driven several times by a
    vehicle with a ray-cast HDL-64E-like LiDAR; runs differ in lane, speed, GNSS/INS drift,
    traffic, parked cars, season and roadworks. Each run is cut into submaps by the same
    path as `pnvlad data prepare` (20 m windows, filter G, 4096 points), and the tree gets
    test regions and splits, ready for `pnvlad train`, `pnvlad eval` and `pnvlad index build`.

    Writes OUT/AREA/RUN/pointcloud_20m_10overlap/ and pointcloud_20m/ with their CSVs,
    OUT/AREA/test_regions.json, OUT/splits.json and OUT/synth.json. The same seed gives the
    same bytes.

    Examples:

        pnvlad synth --preset demo --out city/

        pnvlad synth --preset benchmark --seed 1 --out bench/ --preview bench/preview/

        pnvlad synth --refresh-truth --out bench/
    """
    from pnvlad_service.synth.generate import generate
    from pnvlad_service.synth.generate import refresh_truth as refresh

    with user_errors():
        if refresh_truth:
            rows = refresh(out, trajectories=trajectories, progress=progress)
            typer.echo(f"refreshed the true poses and keyframes' motion of {rows} submaps in {out}")
            return
        summary = generate(
            preset,
            out,
            seed=seed,
            workers=workers or None,
            trajectories=trajectories,
            overwrite=overwrite,
            progress=progress,
        )
        q = sum(summary["queries"].values())
        anchors = sum(summary["training_anchors"].values())
        typer.echo(
            f"wrote {out}: {summary['submaps']} submaps from {len(summary['runs'])} runs in "
            f"{summary['seconds']:.0f} s ({summary['submaps_per_second']:.1f} submaps/s, "
            f"{summary['workers']} workers); {anchors} training anchors, {q} queries"
        )
        if preview is not None:
            from pnvlad_service.synth.preview import render_previews

            for p in render_previews(out, preview, seed=seed):
                typer.echo(f"preview: {p}")
