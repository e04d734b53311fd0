"""Who is near whom: radius searches in (northing, easting).

Distances are Euclidean in (northing, easting), computed as ``dn² + de² <= r²`` in float64 from
coordinate differences, so points exactly r metres away along one axis are inside.
"""

from __future__ import annotations

import numpy as np


def within_radius(
    ref_n: np.ndarray,
    ref_e: np.ndarray,
    q_n: np.ndarray,
    q_e: np.ndarray,
    radius: float,
    chunk: int = 4096,
) -> list[np.ndarray]:
    """For each query point, the sorted int64 indices of reference points with
    ``(dn)² + (de)² <= radius²`` (float64, inclusive). Coordinates in UTM metres."""
    from scipy.spatial import cKDTree

    ref_n = np.asarray(ref_n, np.float64)
    ref_e = np.asarray(ref_e, np.float64)
    q_n = np.asarray(q_n, np.float64)
    q_e = np.asarray(q_e, np.float64)
    if len(ref_n) == 0 or len(q_n) == 0:
        return [np.empty(0, np.int64) for _ in range(len(q_n))]
    # A local origin keeps the tree's arithmetic small; the exact test below decides, so the
    # tree only has to propose a superset (a slightly larger radius). Queries go in chunks to
    # bound the memory of the candidate pairs.
    on, oe = float(ref_n.min()), float(ref_e.min())
    tree = cKDTree(np.column_stack([ref_n - on, ref_e - oe]))
    r_tree = radius * (1 + 1e-9) + 1e-6
    r2 = float(radius) ** 2
    out: list[np.ndarray] = []
    for s in range(0, len(q_n), chunk):
        qn, qe = q_n[s : s + chunk], q_e[s : s + chunk]
        qtree = cKDTree(np.column_stack([qn - on, qe - oe]))
        pairs = tree.sparse_distance_matrix(qtree, r_tree, output_type="ndarray")
        ri = pairs["i"].astype(np.int64)
        qi = pairs["j"].astype(np.int64)
        keep = (ref_n[ri] - qn[qi]) ** 2 + (ref_e[ri] - qe[qi]) ** 2 <= r2
        # sort by (query, reference) through one int64 key: faster than a two-key lexsort
        key = qi[keep] * len(ref_n) + ri[keep]
        key.sort()
        qi, ri = np.divmod(key, len(ref_n))
        counts = np.bincount(qi, minlength=len(qn))
        out.extend(np.split(ri, np.cumsum(counts)[:-1]))
    return out
