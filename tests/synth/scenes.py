"""Hand-placed geometry the sensor tests cast against: flat ground, empty primitive sets, and a
sensor that fails only where a test asks it to."""

from __future__ import annotations

import numpy as np

from pnvlad_service.synth.world import KIND_BUILDING, Boxes, Cylinders, Ellipsoids, Ground, Scene

FLAT = Ground(np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
NO_BOX = Boxes(
    np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int8)
)
NO_CYL = Cylinders(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0, np.int8))
NO_ELL = Ellipsoids(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8))
#: A sensor that fails only where a test asks it to.
CLEAN = {"range_noise": 0.0, "dropout": 0.0, "min_range": 0.5}


def four_walls() -> Scene:
    """A room of four building walls 12 m from the origin (0.5 m thick, 26 m long, from 3 m
    below the ground to 10 m up): every column of a sweep meets a wall."""
    walls = Boxes(
        np.array([[12.0, 0.0], [-12.0, 0.0], [0.0, 12.0], [0.0, -12.0]]),
        np.array([[0.5, 13.0], [0.5, 13.0], [13.0, 0.5], [13.0, 0.5]]),
        np.tile([[-3.0, 10.0]], (4, 1)),
        np.zeros(4),
        np.full(4, KIND_BUILDING, np.int8),
    )
    return Scene(walls, NO_CYL, NO_ELL)
