"""Helpers shared by the command modules: logging set-up and error reporting."""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

import typer

log = logging.getLogger("pnvlad")


def setup_logging(verbosity: int) -> None:
    """Configure the root logger: WARNING at -1, INFO at 0, DEBUG at 1 and above."""
    level = (
        logging.INFO if verbosity == 0 else (logging.DEBUG if verbosity > 0 else logging.WARNING)
    )
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )
    # faiss announces which SIMD build it loaded at INFO on every start: noise for users.
    logging.getLogger("faiss.loader").setLevel(max(level, logging.WARNING))


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn the library's expected errors into a one-line message and exit code 2.

    Unexpected exceptions are not caught: a traceback is the right thing for a bug.
    """
    from pnvlad_service.errors import PnvladError

    try:
        yield
    except (PnvladError, FileNotFoundError, FileExistsError, IsADirectoryError) as exc:
        typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
        raise typer.Exit(code=2) from None
