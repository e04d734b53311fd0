"""The check every point cloud passes when it is read or written: ``[N, 3]``, non-empty, finite."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError


def validate_points(points: np.ndarray, source: str | Path | None) -> np.ndarray:
    """Check a cloud is a non-empty, finite ``[N, 3]`` float array; return it unchanged.

    Raises :class:`InputError` naming ``source`` (a file or a field) otherwise.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"expected points of shape [N, 3], got {tuple(points.shape)}", source)
    if points.shape[0] == 0:
        raise InputError("the point cloud is empty", source)
    if not np.isfinite(points).all():
        bad = ~np.isfinite(points).all(axis=1)
        raise InputError(
            f"{int(bad.sum()):,} of {points.shape[0]:,} points have NaN or infinite coordinates",
            source,
        )
    return points
