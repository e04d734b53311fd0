"""Smoothing a map: each entry's descriptor blended with its neighbours' along its drive.

A query recorded between two map entries of a drive sees part of what each of them holds; two
drives of one street also see its far content differently (a crown, a side street one drive
records and the other does not). Blending each map entry's descriptor with the mean of its own
drive's entries within ``radius_m`` metres (``weight`` times the mean, then unit length again)
lets an entry stand for the stretch of street around it rather than for one cut of it. Only the
map changes: queries are embedded as they are, and the index search is unchanged.

The blend is a mean, not a sum, so a map whose entries lie every few metres and one whose
entries lie every 20 m blend with the same weight. By default entries of different drives are
not blended (their positions carry each drive's GNSS error): on the benchmark's protocol, one
drive a database, that is all there is. On a service's map of several drives that agree on
positions, ``across_drives`` blends every drive's entries within the radius, so an entry holds
what each drive saw there; along one drive only gains nothing on such a map (docs/SERVICE.md).
An entry with no neighbour within the radius is left as it is.

Descriptors with ``turns`` headings (:class:`~pnvlad_service.index.manifest.MapRecord`) blend
heading by heading: each ``dim``-wide block with the same block of its neighbours.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError

if TYPE_CHECKING:
    from pnvlad_service.data.tree import Submap


@dataclass(frozen=True)
class Smoothing:
    """``radius_m``: metres within which a drive's entries blend (> 0); ``weight``: the share
    of their mean added to each entry's own descriptor (> 0; 1 gives the neighbours as much
    say as the entry); ``across_drives``: blend the entries of every drive within the radius,
    not only the entry's own (a map whose drives agree on positions: each entry then stands
    for what all the drives saw there)."""

    radius_m: float
    weight: float
    across_drives: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_m) and 0 < self.radius_m <= MAX_RADIUS_M):
            raise InputError(
                f"smoothing radius must be more than 0 and at most {MAX_RADIUS_M:g} m, got "
                f"{self.radius_m!r} (beyond 45 m it blends other places in and loses)",
                "--smooth",
            )
        if not (math.isfinite(self.weight) and self.weight > 0):
            raise InputError(
                f"smoothing weight must be a positive number, got {self.weight!r}",
                "--smooth-weight",
            )

    @classmethod
    def of(
        cls, radius_m: float | None, weight: float | None = None, across_drives: bool = False
    ) -> Smoothing | None:
        """``None`` for no radius (smoothing off), else the checked setting (``weight``
        ``None``: :data:`DEFAULT_WEIGHT`). A weight or ``across_drives`` given without a
        radius is refused rather than ignored."""
        if radius_m is None:
            for given, option in ((weight is not None, "--smooth-weight"),
                                  (across_drives, "--smooth-across-drives")):  # fmt: skip
                if given:
                    raise InputError("needs --smooth R, the radius to blend within", option)
            return None
        w = DEFAULT_WEIGHT if weight is None else float(weight)
        return cls(float(radius_m), w, bool(across_drives))

    @classmethod
    def from_json(cls, doc: Any, source: Any = None) -> Smoothing:
        """Parse a manifest's ``smoothing`` entry; :class:`InputError` naming ``source``."""
        if not isinstance(doc, Mapping) or not all(
            isinstance(doc.get(k), (int, float)) and not isinstance(doc.get(k), bool)
            for k in ("radius_m", "weight")
        ):
            raise InputError("manifest's map smoothing needs numbers radius_m and weight", source)
        across = doc.get("across_drives", False)
        if not isinstance(across, bool):
            raise InputError("manifest's map smoothing across_drives must be true or false", source)
        try:
            return cls(float(doc["radius_m"]), float(doc["weight"]), across)
        except InputError as exc:
            raise InputError(f"manifest's map {exc.detail}", source) from None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"radius_m": self.radius_m, "weight": self.weight}
        if self.across_drives:
            out["across_drives"] = True
        return out

    def apply(
        self, desc: np.ndarray, dim: int, drives: np.ndarray, positions: np.ndarray
    ) -> np.ndarray:
        """:func:`smooth_along_drives` with this setting, on the entries of one area (with
        ``across_drives`` every drive's entries blend, ``drives`` then unused)."""
        if self.across_drives:
            drives = np.zeros(len(desc), dtype=np.int64)
        return smooth_along_drives(desc, dim, drives, positions, self.radius_m, self.weight)

    def apply_to_entries(self, desc: np.ndarray, records: Sequence[Submap]) -> np.ndarray:
        """A bundle's index rows float32 [len(records) * turns, dim] (each record's headings
        one after another) smoothed along the records' drives (dataset and run)."""
        n = len(records)
        if n == 0:
            return desc
        dim = desc.shape[1]
        drives = np.array(
            [r.dataset if self.across_drives else f"{r.dataset}/{r.run}" for r in records]
        )
        positions = np.array([[r.northing, r.easting] for r in records], dtype=np.float64)
        rows = smooth_along_drives(
            desc.reshape(n, -1), dim, drives, positions, self.radius_m, self.weight
        )
        return rows.reshape(-1, dim)

    def check_new_drives(self, have: set[str], records: Sequence[Submap], source: Any) -> None:
        """:class:`InputError` naming ``source`` when ``records`` (to be added to a map smoothed
        this way) extend a drive the map holds (``have``: ``dataset/run`` of its entries): the
        map's entries were blended with their drive's, so a smoothed map takes whole drives;
        a map smoothed across its drives takes none (every entry would change)."""
        if self.across_drives and have:
            raise InputError(
                "the map is smoothed across its drives: build it again with the new runs",
                source,
            )
        old = sorted({f"{r.dataset}/{r.run}" for r in records} & have)
        if old:
            raise InputError(
                f"the map is smoothed along its drives and already holds {old[0]}: add whole "
                "new runs, or build the map again",
                source,
            )


#: The weight ``pnvlad index build --smooth`` and ``pnvlad eval --smooth`` default to.
DEFAULT_WEIGHT = 0.5
#: The largest radius taken: the neighbours a radius finds grow with its square (and with the
#: map's density), and on 20 m submaps 45 m already blends other places in.
MAX_RADIUS_M = 100.0


def neighbours(drives: np.ndarray, positions: np.ndarray, radius_m: float) -> Any:
    """Sparse CSR [N, N] of 1 where entries ``i != j`` are of the same drive and lie within
    ``radius_m`` metres of each other (``positions`` float64 [N, 2], metres)."""
    from scipy import sparse
    from scipy.spatial import cKDTree

    n = len(positions)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    drives = np.asarray(drives)
    for drive in np.unique(drives):
        members = np.flatnonzero(drives == drive)
        if len(members) < 2:
            continue
        pairs = cKDTree(positions[members]).query_pairs(radius_m, output_type="ndarray")
        if len(pairs):
            a, b = members[pairs[:, 0]], members[pairs[:, 1]]
            rows += [a, b]
            cols += [b, a]
    if not rows:
        return sparse.csr_matrix((n, n), dtype=np.float32)
    r, c = np.concatenate(rows), np.concatenate(cols)
    return sparse.csr_matrix((np.ones(len(r), dtype=np.float32), (r, c)), shape=(n, n))


def smooth_along_drives(
    desc: np.ndarray,
    dim: int,
    drives: np.ndarray,
    positions: np.ndarray,
    radius_m: float,
    weight: float,
) -> np.ndarray:
    """float32 [N, W]: each row of ``desc`` [N, W] (``W // dim`` unit blocks, one a heading)
    plus ``weight`` times the mean of its drive's rows within ``radius_m`` metres, each block
    brought back to unit length. ``drives`` [N] names each row's drive, ``positions`` [N, 2]
    its place in metres. Rows without a neighbour come back unchanged (renormalised)."""
    desc = np.asarray(desc, dtype=np.float32)
    n, width = desc.shape
    if width % dim:
        raise ValueError(f"descriptor width {width} is not a multiple of {dim}")
    if len(drives) != n or len(positions) != n:
        raise ValueError(f"{n} descriptors but {len(drives)} drives and {len(positions)} places")
    adj = neighbours(drives, np.asarray(positions, dtype=np.float64), radius_m)
    counts = np.asarray(adj.sum(axis=1)).reshape(-1, 1)
    mean = np.asarray(adj @ desc) / np.maximum(counts, 1.0)
    out = (desc + np.float32(weight) * mean.astype(np.float32)).reshape(n, -1, dim)
    norm = np.linalg.norm(out, axis=2, keepdims=True)
    return (out / np.maximum(norm, 1e-12)).reshape(n, width).astype(np.float32)
