"""Read the published benchmark pickles without running their code; write plain ones.

Unpickling can call any importable function (``os.system`` included), so a pickle from the
internet is a program, not data. The published split files hold only dicts, lists, ints,
floats, strings, bools and ``None``, which the pickle protocol encodes with opcodes that need no
class at all. ``safe_load`` uses an unpickler whose ``find_class`` refuses every class, so a
file that names any global (a class, a function, ``numpy.float64`` scalars, ``collections``
types) is refused with an ``InputError`` naming the file and the global, before anything runs.

Protocols 0 to 5 are read. Sets and frozensets (protocol 4+ opcodes that need no class) are
accepted too; tuples and bytes load as themselves.
"""

from __future__ import annotations

import io
import logging
import pickle
from pathlib import Path
from typing import Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_open

log = logging.getLogger(__name__)

#: Plain types ``dump_plain`` accepts (recursively).
PLAIN_TYPES = (dict, list, tuple, str, int, float, bool, bytes, type(None))


class _RefusingUnpickler(pickle.Unpickler):
    """An unpickler that refuses every global: no class is ever imported or called."""

    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(
            f"refused to load global '{module}.{name}': only plain dicts, lists, numbers and "
            "strings are accepted"
        )

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("refused a persistent id: not a plain-data pickle")


def safe_loads(data: bytes, source: str | Path | None = None) -> Any:
    """Unpickle ``data`` refusing every class; errors become ``InputError`` naming ``source``."""
    stream = io.BytesIO(data)
    try:
        obj = _RefusingUnpickler(stream).load()
    except pickle.UnpicklingError as exc:
        msg = str(exc)
        if msg.startswith("refused"):
            raise InputError(msg, source=source) from None
        raise InputError(f"not a valid pickle ({msg})", source=source) from None
    except EOFError:
        raise InputError("truncated or empty pickle (ran out of data)", source=source) from None
    except (ValueError, KeyError, IndexError, TypeError, AttributeError, OverflowError) as exc:
        # Malformed opcode streams surface as assorted built-in errors.
        raise InputError(
            f"not a valid pickle ({type(exc).__name__}: {exc})", source=source
        ) from None
    rest = stream.read()
    if rest.strip(b"\x00"):
        log.warning("%s: %d bytes after the end of the pickle ignored", source, len(rest))
    return obj


def safe_load(path: str | Path) -> Any:
    """Load a pickle file holding only plain data; refuse any class.

    Returns the object (dicts, lists, ints, floats, strings, bools, ``None``, tuples, bytes,
    sets). Raises ``InputError`` naming the file when the file is missing, truncated, not a
    pickle, or names any global (class or function).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("pickle file not found", source=path) from None
    except IsADirectoryError:
        raise InputError("is a directory, expected a pickle file", source=path) from None
    return safe_loads(data, source=path)


def _check_plain(obj: Any, where: str = "object") -> None:
    # Iterative so that deep nesting cannot overflow the stack.
    stack = [(obj, where)]
    while stack:
        o, w = stack.pop()
        if type(o) not in PLAIN_TYPES:
            raise InputError(
                f"{type(o).__module__}.{type(o).__qualname__} is not a plain type "
                "(dict, list, tuple, str, int, float, bool, bytes, None); convert it first "
                "(e.g. numpy values with int()/float()/.tolist())",
                source=w,
            )
        if type(o) is dict:
            for k, v in o.items():
                stack.append((k, f"{w} key"))
                stack.append((v, f"{w}[{k!r}]"))
        elif type(o) in (list, tuple):
            stack.extend((v, f"{w}[{i}]") for i, v in enumerate(o))


def dump_plain(obj: Any, path: str | Path, protocol: int = 4) -> None:
    """Write ``obj`` as a pickle atomically, after checking it holds only plain types.

    Only exact ``dict``, ``list``, ``tuple``, ``str``, ``int``, ``float``, ``bool``, ``bytes``
    and ``None`` are allowed (a numpy scalar or array raises ``InputError``), so the file loads
    with ``safe_load`` and with the published code alike. Protocol 4 by default (Python 3.4+,
    read by the published Python 3 scripts).
    """
    _check_plain(obj)
    data = pickle.dumps(obj, protocol=protocol)
    with atomic_open(path, "wb") as fh:
        fh.write(data)
