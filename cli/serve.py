"""`pnvlad serve` and `pnvlad localize`."""

from __future__ import annotations

import typer


def serve() -> None:
    """Serve (not implemented yet)."""
    raise typer.Exit(1)


def localize() -> None:
    """Localize (not implemented yet)."""
    raise typer.Exit(1)
