"""The entry point every benchmark script ends with: ``run(main)``; and where the shared real
scans are by default (:func:`real_scans_default`).

The library's expected errors (a missing optional dependency, a wrong input) end a script as
they end a ``pnvlad`` command: one line, ``error: ...``, on stderr and exit status 2, not a
traceback (cli/common.py's ``user_errors``). Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from pnvlad_service.errors import PnvladError


def run(main: Callable[[], int | None]) -> NoReturn:
    """Call ``main()`` and exit with its return value (None: 0); a ``PnvladError`` (such as
    ``MissingDependencyError``, naming the extra to install) exits 2 with its one line."""
    try:
        status = main()
    except PnvladError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(status)


def real_scans_default() -> str:
    """The folder of the shared real scans: ``$PNVLAD_REAL_SCANS``, else
    ``../shared/data/real_scans`` beside the checkout (the scripts' ``--scans`` / ``--real``
    default)."""
    repo = Path(__file__).resolve().parents[1]
    return os.environ.get("PNVLAD_REAL_SCANS") or str(
        repo.parent / "shared" / "data" / "real_scans"
    )
