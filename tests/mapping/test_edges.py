"""The edges' covariance floors: the odometry's turn has its own, tighter than the closures'."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest


def _yaw_sigmas_deg(tiny: Path, **floors: float) -> np.ndarray:
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, odometry_edges
    from pnvlad_service.mapping.nodes import MapNodes, read_tree_nodes

    nodes = read_tree_nodes(tiny, "keyframe")
    run = nodes.runs[0]
    cut = slice(0, 4)
    short = replace(
        run,
        stamps=run.stamps[cut],
        poses=run.poses[cut],
        truth=None if run.truth is None else run.truth[cut],
        frames=run.frames[cut],
        paths=None if run.paths is None else run.paths[cut],
        clouds=None if run.clouds is None else run.clouds[cut],
        recorded_motion=None if run.recorded_motion is None else run.recorded_motion[cut],
    )
    one = MapNodes([short])
    config = EdgeConfig(**floors)
    edges = [e for e in odometry_edges(one, Clouds.for_odometry(one, config), config) if e.accepted]
    assert edges, "no odometry step of the tiny city registered"
    return np.array([math.degrees(math.sqrt(e.covariance[5, 5])) for e in edges])


def test_the_odometry_takes_its_own_yaw_floor_not_the_closures(tiny: Path) -> None:
    loose = _yaw_sigmas_deg(tiny, min_sigma_deg=0.5, odometry_min_sigma_deg=0.02)
    assert (loose >= 0.02).all() and (loose < 0.5).all()
    tight = _yaw_sigmas_deg(tiny, min_sigma_deg=0.01, odometry_min_sigma_deg=0.3)
    assert (tight >= 0.3).all()
    # the registration's own variance stays under the floor: sqrt(a^2 + f^2) >= f
    assert tight == pytest.approx(np.sqrt(loose**2 - 0.02**2 + 0.3**2), rel=1e-6)
