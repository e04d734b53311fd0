"""`pnvlad train`."""

from __future__ import annotations

import typer


def train() -> None:
    """Train the encoder (not implemented yet)."""
    raise typer.Exit(1)
