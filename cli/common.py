"""Helpers shared by the command modules: logging set-up and error reporting."""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator
from typing import Any

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
    from pnvlad_service.errors import MissingDependencyError, PnvladError

    try:
        yield
    except (PnvladError, FileNotFoundError, FileExistsError, IsADirectoryError) as exc:
        typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
        raise typer.Exit(code=2) from None
    except ModuleNotFoundError as exc:
        # torch (and onnx, for the export) are the `torch` extra: whatever needs them says so
        # in one line rather than a traceback from deep inside the library.
        top = (exc.name or "").split(".")[0]
        if top not in TORCH_EXTRA:
            raise
        missing = MissingDependencyError(top, "torch", _command_path())
        typer.secho(f"error: {missing}", err=True, fg=typer.colors.RED)
        raise typer.Exit(code=2) from None


#: The modules of the `torch` extra (pyproject.toml).
TORCH_EXTRA = ("torch", "onnx")


def _command_path() -> str:
    """The running command, e.g. ``pnvlad train`` (Typer 0.20 and later carry their own copy of
    click, whose context stack is not click's)."""
    try:
        from typer._click.globals import get_current_context
    except ImportError:
        from click import get_current_context
    ctx = get_current_context(silent=True)
    return ctx.command_path if ctx is not None else "this command"


# Options that several commands take, declared once so that a flag means the same everywhere:
# -m/--model is always a model (a model directory or the training run that made it), -r/--root
# always a benchmark tree, -c only ever --config (pnvlad train).
MODEL_HELP = (
    "A model directory (model.json + model.safetensors, a training checkpoint included), a "
    "training run directory (its model/ is used) or pretrained:NAME (pnvlad model list)."
)


def model_option(default: Any = None, help: str = "", panel: str | None = None) -> Any:
    """``-m/--model`` (``--checkpoint`` also accepted): resolve the value with
    ``pnvlad_service.models.store.resolve_model_dir``."""
    return typer.Option(
        default,
        "--model",
        "--checkpoint",
        "-m",
        help=f"{help} {MODEL_HELP}".strip(),
        rich_help_panel=panel,
    )


def progress_option() -> Any:
    """``--progress/--no-progress`` (on by default), the same on every long command."""
    return typer.Option(
        True,
        "--progress/--no-progress",
        help="Show progress on stderr: a bar on a terminal, plain lines in a log.",
    )


def root_option(default: Any = None, panel: str | None = None) -> Any:
    """``-r/--root``: a benchmark tree."""
    return typer.Option(
        default,
        "--root",
        "-r",
        help="Benchmark tree root (holds oxford/, ...).",
        rich_help_panel=panel,
    )


def splits_option(panel: str | None = None) -> Any:
    """``--splits``: our splits JSON."""
    return typer.Option(
        None,
        "--splits",
        help="Splits JSON from 'pnvlad data splits' (default: built from the tree).",
        rich_help_panel=panel,
    )


def pickles_option(help: str, panel: str | None = None) -> Any:
    """``--pickles``: the published pickles instead of ``--splits``."""
    return typer.Option(None, "--pickles", help=help, rich_help_panel=panel)


def smooth_option(panel: str | None = None) -> Any:
    """``--smooth R``: blend each map entry with its drive's entries within R metres."""
    return typer.Option(
        None,
        "--smooth",
        metavar="METRES",
        help="Smooth the map along its drives: each entry's descriptor blended with the mean of "
        "its own drive's entries within this many metres (25 suits maps of 10-20 m spacing; "
        "docs/SERVICE.md; at most 100). Queries are embedded as they are. Default: off.",
        rich_help_panel=panel,
    )


def smooth_weight_option(panel: str | None = None) -> Any:
    """``--smooth-weight W``: the share of the neighbours' mean in a smoothed entry."""
    from pnvlad_service.index.smoothing import DEFAULT_WEIGHT

    return typer.Option(
        None,
        "--smooth-weight",
        help="With --smooth: the neighbours' mean is added at this weight to each entry's own "
        f"descriptor (1: as much say as the entry). Default: {DEFAULT_WEIGHT:g}.",
        rich_help_panel=panel,
    )


def smooth_across_option(panel: str | None = None) -> Any:
    """``--smooth-across-drives``: blend the entries of every drive, not only the entry's own."""
    return typer.Option(
        False,
        "--smooth-across-drives",
        help="With --smooth: blend the entries of every drive within the radius, not only the "
        "entry's own: each entry stands for what all the drives saw there. For a map whose "
        "drives agree on positions (good GNSS/INS, or pnvlad map align); index add then "
        "refuses the map (build it again).",
        rich_help_panel=panel,
    )
