"""`pnvlad data import`: submaps made elsewhere, in metres, as a benchmark run that verifies."""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli.common import progress_option, user_errors


def import_command(
    src: Path = typer.Argument(..., help="Folder of submaps in metres, one TIMESTAMP.EXT each."),
    locations: Path = typer.Option(
        ...,
        "--locations",
        help="CSV timestamp,northing,easting (UTM metres) of the submaps, one row each.",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder to write (ROOT/DATASET/RUN)."),
    layout: str = typer.Option("oxford", "--layout", help="oxford or inhouse (folder names)."),
    kind: str = typer.Option("test", "--kind", help="train, test or keyframe (which folder)."),
    reader: str = typer.Option(None, "--reader", help="Format of the submaps (default: suffix)."),
    origin: str = typer.Option(
        "position",
        "--origin",
        help="Where the submaps' coordinates start: 'position' (each at its CSV row's "
        "position, axes east, north, up) or 'utm' (absolute UTM coordinates).",
    ),
    height: float = typer.Option(0.0, "--height", help="Height (m) of 'position' origins."),
    g_config: Path = typer.Option(None, "--g-config", help="YAML/JSON of filter G settings."),
    seed: int = typer.Option(0, "--seed", help="Seed of G's random steps (+ the row index)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace what the folder holds."),
    progress: bool = progress_option(),
) -> None:
    """Import submaps from another pipeline so that a bundle of them verifies its answers.

    Each submap goes through the filter G and is written in the benchmark layout with its
    locations CSV and a frame sidecar recording where G's output sits in metres: what
    `pnvlad index build` needs to store the map's geometry, so that `pnvlad serve` registers a
    query against its candidates and answers with a metric pose (docs/PREPARE.md).

    Example:

      pnvlad data import my_submaps/ --locations my_submaps.csv --out mine/city/run1
    """
    with user_errors():
        from pnvlad_service.data.import_submaps import import_submaps
        from pnvlad_service.preprocess.filter_g import GConfig

        config = None if g_config is None else GConfig.from_file(g_config)
        res = import_submaps(
            src,
            locations,
            out,
            layout=layout,
            kind=kind,  # type: ignore[arg-type]
            reader=reader,
            origin=origin,  # type: ignore[arg-type]
            height=height,
            g_config=config,
            seed=seed,
            overwrite=overwrite,
            progress=progress,
        )
    skipped = f", {len(res.skipped)} skipped (see log)" if res.skipped else ""
    typer.echo(f"{res.written} submaps{skipped} -> {res.folder}, {res.csv.name} and its sidecar")


def register(app: typer.Typer) -> None:
    """Add `pnvlad data import` to the `pnvlad data` group."""
    app.command("import")(import_command)
