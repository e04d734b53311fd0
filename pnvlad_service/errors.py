"""Exceptions raised by the library.

Every error about user input names the offending file or field and says what is wrong, so the
CLI can print it as is and exit non-zero, and the server can turn it into a 4xx response.
"""

from __future__ import annotations

from pathlib import Path


class PnvladError(Exception):
    """Base class of every error the library raises on purpose."""


class InputError(PnvladError, ValueError):
    """Bad input data: a file or a field that cannot be used as it is.

    ``source`` is the file path or field name the problem is about (may be ``None``).
    """

    def __init__(self, message: str, source: str | Path | None = None) -> None:
        self.source = None if source is None else str(source)
        self.detail = message
        super().__init__(f"{self.source}: {message}" if self.source else message)


class MissingDependencyError(PnvladError, ImportError):
    """An optional dependency (an extra) is needed for this feature and is not installed."""

    def __init__(self, package: str, extra: str | None, feature: str) -> None:
        # extra None: a core dependency missing from a broken or --no-deps install.
        spec = package if extra is None else f"'pnvlad[{extra}]'"
        super().__init__(
            f"{feature} needs the '{package}' package, which is not installed. "
            f"Install it with: pip install {spec}"
        )


class NotReadyError(PnvladError):
    """A service object was used before it was loaded or after it was closed."""


class CorruptFileError(PnvladError):
    """A file the service already checked and relies on no longer matches its recorded hash
    (e.g. a geometry row fetched at query time): a server fault, not the caller's.

    ``source`` is the file's path.
    """

    def __init__(self, message: str, source: str | Path | None = None) -> None:
        self.source = None if source is None else str(source)
        self.detail = message
        super().__init__(f"{self.source}: {message}" if self.source else message)
