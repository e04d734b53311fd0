"""Helpers shared by the server's tests."""

from __future__ import annotations

import numpy as np

from pnvlad_service.data.scans import read_raw_scans
from pnvlad_service.io.readers import read_points


def held_scan(tiny_maps: dict) -> np.ndarray:
    """A raw scan of the tiny city's held-out run (its fourth), float32 little-endian [N, 4]
    as a client sends it."""
    tree = tiny_maps["tree"]
    scan = read_raw_scans(tree.root / "business" / tiny_maps["query_run"])[3]
    return np.ascontiguousarray(read_points(scan.path, "kitti"), dtype="<f4")
