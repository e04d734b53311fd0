"""The entry point every benchmark script ends with: ``run(main)``.

The library's expected errors (a missing optional dependency, a wrong input) end a script as
they end a ``pnvlad`` command: one line, ``error: ...``, on stderr and exit status 2, not a
traceback (cli/common.py's ``user_errors``). Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
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
