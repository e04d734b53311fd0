"""`pnvlad synth`: the built-in synthetic LiDAR city benchmark."""

from __future__ import annotations

import typer


def synth() -> None:
    """Generate a synthetic benchmark (not implemented yet)."""
    raise typer.Exit(1)
