"""Two behaviour snapshots compared item by item (scripts/behaviour_snapshot.py explains).

Text is compared exactly. Numbers in JSON answers and CSV cells are equal when within
:data:`REL_TOL` of each other (relative; :data:`ABS_TOL` near zero): registration sums its
points' Hessians on two OpenMP threads, in an order that changes from run to run, so what is
derived from them (a pose's ``constraint``, ``sigma_m`` and covariance, the ``confidence``)
differs between two runs of one code in the last digits (about 1e-13 relative, measured). The
diff of a JSON or CSV item shows its numbers rounded to 9 significant digits, so that such
noise does not hide the difference that counts.
"""

from __future__ import annotations

import csv
import difflib
import fnmatch
import io
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Numbers this close (relative) are the same number.
REL_TOL = 1e-9
#: ... and this close (absolute) near zero.
ABS_TOL = 1e-12


@dataclass(frozen=True)
class Allowed:
    """One line of an allow file: a glob of items, ``columns`` (only a CSV's columns may be
    added or reordered) and the reason."""

    pattern: str
    columns: bool
    reason: str

    def matches(self, item: str) -> bool:
        return fnmatch.fnmatchcase(item, self.pattern)


def read_allowed(path: Path | None) -> list[Allowed]:
    """The allow file's entries (SystemExit 2 naming the file, or the line without a reason)."""
    if path is None:
        return []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        print(f"error: {path}: cannot read the allow file ({exc.strerror})", file=sys.stderr)
        raise SystemExit(2) from None
    out = []
    for n, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        item, _, reason = text.partition(" ")
        if not reason.strip():
            print(f"error: {path}:{n}: '{item}' needs a reason after it", file=sys.stderr)
            raise SystemExit(2)
        columns = item.endswith(":columns")
        out.append(Allowed(item.removesuffix(":columns"), columns, reason.strip()))
    return out


def items(root: Path) -> set[str]:
    """A snapshot's items: its files' paths, those whose name starts with a dot left out."""
    found = (p.relative_to(root) for p in root.rglob("*") if p.is_file())
    return {rel.as_posix() for rel in found if not any(n.startswith(".") for n in rel.parts)}


# --------------------------------------------------------------------------------------------
# numbers within the tolerance
# --------------------------------------------------------------------------------------------


def inexact(value: Any) -> float | None:
    """``value`` as a float when it is one that may carry noise: a JSON float, or a CSV cell
    written as a decimal fraction or with an exponent; None for the rest (integers such as
    timestamps and counts, booleans, words), which are compared exactly."""
    if isinstance(value, float):
        return value
    if isinstance(value, str) and any(ch in value for ch in ".eE"):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def same(a: Any, b: Any) -> bool:
    """Whether two parsed JSON values (or CSV cells) are equal, inexact numbers within the
    tolerance."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if a == b:
        return True
    x, y = inexact(a), inexact(b)
    return x is not None and y is not None and math.isclose(x, y, rel_tol=REL_TOL, abs_tol=ABS_TOL)


def rounded(value: Any) -> Any:
    """``value`` with its floats rounded to 9 significant digits (for showing a diff)."""
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v) for v in value]
    if isinstance(value, float) and math.isfinite(value):
        return float(f"{value:.9g}")
    return value


# --------------------------------------------------------------------------------------------
# diffs
# --------------------------------------------------------------------------------------------


def text_diff(a: str, b: str, item: str, limit: int) -> list[str]:
    lines = list(
        difflib.unified_diff(
            a.splitlines(), b.splitlines(), f"A/{item}", f"B/{item}", lineterm="", n=2
        )
    )
    return lines if len(lines) <= limit else [*lines[:limit], f"... {len(lines) - limit} more"]


def json_diff(a: str, b: str, item: str, limit: int) -> list[str] | None:
    """The diff of two JSON texts (numbers rounded), or None when they are the same within
    the tolerance; a text that is not JSON is diffed as text."""
    try:
        ja, jb = json.loads(a), json.loads(b)
    except ValueError:
        return text_diff(a, b, item, limit)
    if same(ja, jb):
        return None

    def show(v: Any) -> str:
        return json.dumps(rounded(v), indent=2, sort_keys=True, ensure_ascii=False)

    return text_diff(show(ja), show(jb), item, limit) or text_diff(a, b, item, limit)


def csv_diff(a: str, b: str, item: str, limit: int) -> tuple[list[str], bool] | None:
    """None when two CSVs are the same (cells within the tolerance), else (the differences,
    whether only columns were added or reordered): the header's change, then a diff of the
    rows on the columns both have."""
    ra, rb = list(csv.reader(io.StringIO(a))), list(csv.reader(io.StringIO(b)))
    ha, hb = (ra[0] if ra else []), (rb[0] if rb else [])
    shared = [c for c in ha if c in hb]

    def project(rows: list[list[str]], header: list[str]) -> list[list[str]]:
        at = [header.index(c) for c in shared]
        return [[r[i] if i < len(r) else "" for i in at] for r in rows[1:]]

    pa, pb = project(ra, ha), project(rb, hb)
    if ha == hb and same(pa, pb):
        return None
    lines = []
    removed, added = [c for c in ha if c not in hb], [c for c in hb if c not in ha]
    if removed:
        lines.append(f"columns only in A: {', '.join(removed)}")
    if added:
        lines.append(f"columns only in B: {', '.join(added)}")
    if not removed and not added and ha != hb:
        lines.append("the columns are in another order")
    values = []
    if not same(pa, pb):

        def show(rows: list[list[str]]) -> str:
            cells = [[c if inexact(c) is None else f"{float(c):.9g}" for c in r] for r in rows]
            return "\n".join(",".join(r) for r in [shared, *cells])

        values = text_diff(show(pa), show(pb), item + " (the columns both have)", limit)
    return lines + values, not removed and not values


# --------------------------------------------------------------------------------------------
# the verdicts
# --------------------------------------------------------------------------------------------


def verdict(a: Path, b: Path, item: str, limit: int) -> tuple[str, list[str], bool]:
    """(``same``, ``same~`` within the tolerance, ``DIFFERS``, ``ONLY IN A`` or ``ONLY IN B``;
    the diff; whether only a CSV's columns changed)."""
    if not (a / item).is_file() or not (b / item).is_file():
        return f"ONLY IN {'A' if (a / item).is_file() else 'B'}", [], False
    ta, tb = ((root / item).read_text(encoding="utf-8", errors="replace") for root in (a, b))
    if ta == tb:
        return "same", [], False
    if item.endswith(".csv"):
        found = csv_diff(ta, tb, item, limit)
        return ("same~", [], False) if found is None else ("DIFFERS", *found)
    if item.endswith(".json"):
        lines = json_diff(ta, tb, item, limit)
        return ("same~", [], False) if lines is None else ("DIFFERS", lines, False)
    return "DIFFERS", text_diff(ta, tb, item, limit), False


def compare(a: Path, b: Path, allow: list[Allowed], limit: int) -> int:
    """Print one verdict an item and the diffs; 1 when an item differs unallowed, else 0."""
    for root in (a, b):
        if not root.is_dir():
            print(f"error: {root}: no such snapshot folder", file=sys.stderr)
            return 2
    every = sorted(items(a) | items(b))
    failed, near, used = 0, 0, set()
    for item in every:
        word, diff, only_columns = verdict(a, b, item, limit)
        if word.startswith("same"):
            near += word == "same~"
            tail = f" (numbers within {REL_TOL:g})" if word == "same~" else ""
            print(f"{word:9} {item}{tail}")
            continue
        rule = next((r for r in allow if r.matches(item)), None)
        if rule is not None and (not rule.columns or only_columns):
            used.add(rule)
            print(f"allowed   {item}: {word.lower()} ({rule.reason})")
        else:
            failed += 1
            print(f"{word:9} {item}")
        for line in diff:
            print(f"    {line}")
    for rule in allow:
        if rule not in used:
            print(f"note: allowed but not needed: {rule.pattern}{':columns' * rule.columns}")
    print(
        f"{len(every)} items: {failed} differ"
        + (" (not allowed)" if failed else "")
        + (f"; {near} the same within {REL_TOL:g}" if near else "")
    )
    return 1 if failed else 0
