"""`pnvlad eval`."""

from __future__ import annotations

import typer


def evaluate() -> None:
    """Evaluate (not implemented yet)."""
    raise typer.Exit(1)
