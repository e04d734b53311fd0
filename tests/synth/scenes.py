"""Hand-placed geometry the sensor tests cast against: flat ground, empty primitive sets, and a
sensor that fails only where a test asks it to."""

from __future__ import annotations

import numpy as np

from pnvlad_service.synth.world import Boxes, Cylinders, Ellipsoids, Ground

FLAT = Ground(np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
NO_BOX = Boxes(
    np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int8)
)
NO_CYL = Cylinders(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0, np.int8))
NO_ELL = Ellipsoids(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8))
#: A sensor that fails only where a test asks it to.
CLEAN = {"range_noise": 0.0, "dropout": 0.0, "min_range": 0.5}
