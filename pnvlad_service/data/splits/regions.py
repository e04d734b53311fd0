"""Test regions: the squares of the benchmark that hold the queries and are kept out of training.

A submap is inside when, for some centre (cn, ce), ``cn - w < northing < cn + w`` and
``ce - w < easting < ce + w`` (strict; w = 150 m by default). The published regions (Oxford, the
in-house areas) are built in; a tree may carry its own in ``<dataset>/test_regions.json``
(docs/SPLITS.md), or the caller passes them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text

REGIONS_FORMAT = "pnvlad-test-regions"
REGIONS_FILE = "test_regions.json"

#: Half side of a published test square, metres.
HALF_SIZE = 150.0

#: The four Oxford test regions, (northing, easting) UTM metres.
OXFORD_CENTRES: tuple[tuple[float, float], ...] = (
    (5735712.768124, 620084.402381),
    (5735611.299219, 620540.270327),
    (5735237.358209, 620543.094379),
    (5734749.303802, 619932.693364),
)
#: The in-house areas' test regions (generate_test_sets.py); business: the whole area.
INHOUSE_CENTRES: dict[str, tuple[tuple[float, float], ...]] = {
    "university": (
        (363621.292362, 142864.19756),
        (364788.795462, 143125.746609),
        (363597.507711, 144011.414174),
    ),
    "residential": (
        (360895.486453, 144999.915143),
        (362357.024536, 144894.825301),
        (361368.907155, 145209.663042),
    ),
}


@dataclass(frozen=True)
class TestRegions:
    """Square test regions: ``centres`` (northing, easting) UTM metres, each ± ``half_size``.

    ``everything=True`` puts every submap inside (the in-house business district).
    """

    __test__ = False  # not a pytest class

    centres: tuple[tuple[float, float], ...] = ()
    half_size: float = HALF_SIZE
    everything: bool = False

    @classmethod
    def oxford(cls) -> TestRegions:
        return cls(OXFORD_CENTRES, HALF_SIZE)

    def contains(self, northing: np.ndarray, easting: np.ndarray) -> np.ndarray:
        """bool [N]: inside any region, by the strict published test
        ``c - w < x < c + w`` on both axes."""
        n = np.asarray(northing, dtype=np.float64)
        e = np.asarray(easting, dtype=np.float64)
        if self.everything:
            return np.ones(n.shape, dtype=bool)
        inside = np.zeros(n.shape, dtype=bool)
        w = float(self.half_size)
        for cn, ce in self.centres:
            inside |= (cn - w < n) & (n < cn + w) & (ce - w < e) & (e < ce + w)
        return inside

    def to_dict(self) -> dict[str, Any]:
        return {
            "centres": [[float(a), float(b)] for a, b in self.centres],
            "half_size": float(self.half_size),
            "all": bool(self.everything),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str | Path = "regions") -> TestRegions:
        try:
            centres = tuple((float(a), float(b)) for a, b in d.get("centres", []))
            half = float(d.get("half_size", HALF_SIZE))
            everything = bool(d.get("all", False))
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"bad test regions ({exc}); expected centres [[northing, easting], ...]", source
            ) from None
        if not math.isfinite(half) or half <= 0:
            raise InputError(f"half_size must be a positive number of metres, got {half}", source)
        if not all(math.isfinite(v) for c in centres for v in c):
            raise InputError("test region centres must be finite numbers", source)
        return cls(centres, half, everything)


def builtin_regions(dataset: str, group: str) -> TestRegions | None:
    """The published test regions for Oxford and the in-house areas, or ``None``."""
    if dataset == "oxford":
        return TestRegions.oxford()
    if dataset == "inhouse_datasets":
        if group == "business":
            return TestRegions(everything=True)
        if group in INHOUSE_CENTRES:
            return TestRegions(INHOUSE_CENTRES[group], HALF_SIZE)
    return None


def published_regions_on(dataset: str, northing: np.ndarray, easting: np.ndarray) -> TestRegions:
    """The published test regions of ``dataset`` (``oxford``) for a route laid over them (a
    synthetic area placed at Oxford's UTM coordinates): float64 ``northing``, ``easting`` [N]
    of the route. :class:`InputError` naming ``test_regions`` where the benchmark published
    none for ``dataset``, or where the route crosses none of them (no queries) or lies wholly
    inside them (nothing to train on)."""
    regions = builtin_regions(dataset, dataset)
    if regions is None or regions.everything:
        raise InputError(
            f"the benchmark published test regions for oxford only, not {dataset!r} (name the "
            "area oxford, or choose the regions on the route)",
            "test_regions",
        )
    inside = regions.contains(northing, easting)
    if not inside.any() or inside.all():
        where = "crosses none of" if not inside.any() else "lies wholly inside"
        raise InputError(
            f"the route {where} {dataset}'s published test regions: place the area (its origin "
            "and size) so that the route passes through some of them",
            "test_regions",
        )
    return regions


def load_regions(path: str | Path) -> dict[str, TestRegions] | TestRegions:
    """Read a test-regions file: JSON (docs/SPLITS.md) or CSV ``[dataset,]northing,easting
    [,half_size]``. Returns one ``TestRegions`` for every dataset, or a mapping name -> regions.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("test regions file not found", source=path) from None
    if path.suffix.lower() == ".csv":
        return _regions_from_csv(text, path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc})", source=path) from None
    if not isinstance(doc, dict):
        raise InputError("expected a JSON object", source=path)
    if doc.get("format", REGIONS_FORMAT) != REGIONS_FORMAT:
        raise InputError(f"format is {doc.get('format')!r}, expected {REGIONS_FORMAT!r}", path)
    if "regions" in doc:
        if not isinstance(doc["regions"], dict):
            raise InputError("'regions' must map names to region sets", source=path)
        return {str(k): TestRegions.from_dict(v, path) for k, v in doc["regions"].items()}
    return TestRegions.from_dict(doc, path)


def _regions_from_csv(text: str, path: Path) -> dict[str, TestRegions] | TestRegions:
    import csv

    rows = list(csv.DictReader(text.splitlines()))
    if not rows or not {"northing", "easting"} <= set(rows[0]):
        raise InputError("expected a CSV with columns northing,easting[,half_size][,dataset]", path)
    groups: dict[str, list[tuple[float, float]]] = {}
    halves: dict[str, float] = {}
    for k, r in enumerate(rows, start=2):
        name = (r.get("dataset") or "").strip() or "*"
        try:
            c = (float(r["northing"]), float(r["easting"]))
            h = float(r["half_size"]) if (r.get("half_size") or "").strip() else HALF_SIZE
        except (TypeError, ValueError):
            raise InputError(
                f"line {k}: northing/easting/half_size must be numbers", path
            ) from None
        if halves.setdefault(name, h) != h:
            raise InputError(
                f"line {k}: one half_size per dataset, got {h} and {halves[name]}", path
            )
        groups.setdefault(name, []).append(c)
    out = {
        n: TestRegions.from_dict({"centres": c, "half_size": halves[n]}, path)
        for n, c in groups.items()
    }
    return out["*"] if list(out) == ["*"] else out


def save_regions(path: str | Path, regions: TestRegions | Mapping[str, TestRegions]) -> None:
    """Write a test-regions JSON file atomically (one set, or a mapping name -> set)."""
    doc: dict[str, Any] = {"format": REGIONS_FORMAT, "version": 1}
    if isinstance(regions, TestRegions):
        doc.update(regions.to_dict())
    else:
        doc["regions"] = {k: v.to_dict() for k, v in regions.items()}
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def resolve_regions(
    tree: BenchmarkTree,
    dataset: str,
    group: str,
    regions: TestRegions | Mapping[str, TestRegions] | None = None,
) -> TestRegions:
    """The test regions of ``group`` (an area or the dataset itself) in ``dataset``.

    In order: ``regions`` given (one set, or a mapping by group or dataset name), the tree's
    ``<root>/<dataset>/test_regions.json``, the published regions (Oxford, in-house areas).
    """
    for candidate in (regions, _tree_regions(tree, dataset)):
        if candidate is None:
            continue
        if isinstance(candidate, TestRegions):
            return candidate
        for key in (group, dataset, "*"):
            if key in candidate:
                return candidate[key]
    found = builtin_regions(dataset, group)
    if found is None:
        raise InputError(
            f"no test regions known for {group!r}: pass --regions FILE or write "
            f"{dataset}/{REGIONS_FILE} (see docs/SPLITS.md)",
            source=tree.root / dataset,
        )
    return found


def _tree_regions(tree: BenchmarkTree, dataset: str) -> dict[str, TestRegions] | TestRegions | None:
    p = tree.root / dataset / REGIONS_FILE
    return load_regions(p) if p.is_file() else None
