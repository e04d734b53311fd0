"""`pnvlad data`: everything between raw LiDAR files and a benchmark tree with its splits."""

from __future__ import annotations

import typer

from pnvlad_cli import data_bench, data_import, data_prepare, data_preprocess

app = typer.Typer(
    rich_markup_mode="markdown",
    help=(
        "Turn raw LiDAR into benchmark data: preprocess one scan with the filter G, prepare a "
        "recorded drive into submaps, check a benchmark tree, build training tuples and "
        "evaluation sets."
    ),
    no_args_is_help=True,
)

data_preprocess.register(app)
data_prepare.register(app)
data_import.register(app)
data_bench.register(app)
