"""Atomic writes: output appears complete under its final name, or not at all.

Everything the project writes (submaps, CSVs, splits, checkpoints, index bundles) goes through
these helpers: the data is written to a temporary file in the destination directory, flushed,
fsync'ed and then renamed over the final path, which is atomic on POSIX file systems.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb", **kwargs) -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; rename it to ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    if "r" in mode or "a" in mode:
        raise ValueError(f"atomic_open is for writing only, got mode {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates files 0600; give the result the permissions a plain open() would.
        os.fchmod(fd, 0o666 & ~_UMASK)
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once at import: os.umask can only be read by setting it, which is not thread-safe.
_UMASK = _read_umask()


def default_permissions(path: str | Path) -> None:
    """Give ``path`` the mode a plain open() (or mkdir) would have, under the process's umask.

    For files that a library writes itself with a tighter mode: safetensors' ``save_file``
    creates them 0600, so a model trained by one user could not be read by another, such as the
    container image's uid 10001 with the model mounted read-only.
    """
    path = Path(path)
    path.chmod((0o777 if path.is_dir() else 0o666) & ~_UMASK)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)


def csv_cell(value: object, digits: int | None = None) -> str:
    """A CSV cell of a report's row: empty for None, ``true``/``false``, a float's repr (rounded
    to ``digits`` places when given)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value if digits is None else round(value, digits))
    return str(value)


def atomic_write_rows(
    rows: Iterable[object], columns: Sequence[str], path: str | Path, digits: int | None = None
) -> Path:
    """Rows (objects with an attribute a column) as a CSV with a header, written atomically."""
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow(columns)
    for r in rows:
        out.writerow(csv_cell(getattr(r, c), digits) for c in columns)
    path = Path(path)
    atomic_write_text(path, buf.getvalue())
    return path


@contextlib.contextmanager
def atomic_directory(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Build a directory under a temporary name and rename it to ``path`` on success.

    Yields the temporary directory to fill. An interrupted build leaves only a hidden
    ``.<name>.tmp*`` directory, never something under the final name that looks complete.
    With ``overwrite`` an existing ``path`` is replaced (moved aside, then removed).
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass overwrite to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    tmp.chmod(0o777 & ~_UMASK)
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def read_csv_text(path: str | Path, what: str, encoding: str = "utf-8") -> str:
    """The text of a CSV file; :class:`~pnvlad_service.errors.InputError` naming the file when
    it is missing (``what`` not found) or not text."""
    from pnvlad_service.errors import InputError

    try:
        return Path(path).read_text(encoding=encoding)
    except FileNotFoundError:
        raise InputError(f"{what} not found", source=path) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"not a text CSV ({exc.reason})", source=path) from None


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes, read ``chunk`` bytes at a time."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()
