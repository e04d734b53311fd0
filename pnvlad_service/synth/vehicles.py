"""Vehicles of several shapes: a car is a body on its wheels' clearance and a cabin on top, a van
or a lorry one tall box, where the first benchmarks had one box for every vehicle.

A shape is drawn per vehicle (:func:`draw_shapes`: saloons, hatchbacks, estates, SUVs and vans)
and laid as boxes at any place and heading (:func:`vehicle_boxes`), so that parked cars can
change shape from run to run (another car in the same slot) and moving ones keep theirs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pnvlad_service.synth.world import KIND_CAR, Boxes

#: (name, share, length m, width m, height m, cabin's share of the length, its shift back as
#: a share of the length): cars have a cabin over a body; vans (cabin share 0) are one box.
Shape = tuple[str, float, tuple[float, float], float, tuple[float, float], float, float]
SHAPES: tuple[Shape, ...] = (
    ("saloon", 0.30, (4.4, 4.9), 1.80, (1.40, 1.50), 0.45, 0.05),
    ("hatchback", 0.25, (3.8, 4.3), 1.75, (1.45, 1.55), 0.55, 0.12),
    ("estate", 0.15, (4.5, 4.9), 1.80, (1.45, 1.55), 0.62, 0.12),
    ("suv", 0.20, (4.4, 4.9), 1.90, (1.65, 1.85), 0.60, 0.10),
    ("van", 0.10, (5.0, 6.5), 2.00, (2.10, 2.70), 0.0, 0.0),
)
#: Height of a body's underside above the road (the wheels' clearance), metres.
CLEARANCE_M = 0.3
#: Share of a car's height that is its body (the rest is the cabin).
BODY_SHARE = 0.58


@dataclass
class Shapes:
    """Per vehicle: half length and half width [M, 2], height [M], cabin length share [M] (0:
    one box) and its shift back [M]."""

    half: np.ndarray
    height: np.ndarray
    cabin: np.ndarray
    shift: np.ndarray

    def take(self, keep: np.ndarray) -> Shapes:
        """The shapes of the vehicles ``keep`` selects (a mask or indices)."""
        return Shapes(self.half[keep], self.height[keep], self.cabin[keep], self.shift[keep])


def draw_shapes(rng: np.random.Generator, n: int) -> Shapes:
    """``n`` vehicle shapes drawn from :data:`SHAPES` by their shares."""
    share = np.array([s[1] for s in SHAPES])
    which = rng.choice(len(SHAPES), size=n, p=share / share.sum())
    u = rng.random((n, 2))
    half = np.empty((n, 2))
    height = np.empty(n)
    cabin = np.empty(n)
    shift = np.empty(n)
    for k, (_, _, length, width, tall, cab, back) in enumerate(SHAPES):
        sel = which == k
        half[sel, 0] = (length[0] + u[sel, 0] * (length[1] - length[0])) / 2
        half[sel, 1] = width / 2
        height[sel] = tall[0] + u[sel, 1] * (tall[1] - tall[0])
        cabin[sel] = cab
        shift[sel] = back
    return Shapes(half, height, cabin, shift)


def vehicle_boxes(
    center: np.ndarray, yaw: np.ndarray, ground_z: np.ndarray, shapes: Shapes
) -> Boxes:
    """The boxes of vehicles at ``center`` [M, 2] heading ``yaw`` [M] on the ground at
    ``ground_z`` [M]: each car's body and cabin, each van's one box (kind ``KIND_CAR``)."""
    n = len(center)
    top = ground_z + shapes.height
    car = shapes.cabin > 0
    body_top = ground_z + CLEARANCE_M + BODY_SHARE * (shapes.height - CLEARANCE_M)
    body_top = np.where(car, body_top, top)
    body = Boxes(
        center.copy(),
        shapes.half.copy(),
        np.stack([ground_z + CLEARANCE_M, body_top], 1),
        np.asarray(yaw, dtype=np.float64).copy(),
        np.full(n, KIND_CAR, np.int8),
    )
    fwd = np.stack([np.cos(yaw), np.sin(yaw)], 1)[car]
    back = (shapes.shift * 2 * shapes.half[:, 0])[car, None]
    cab_half = np.stack([shapes.cabin * shapes.half[:, 0], 0.88 * shapes.half[:, 1]], 1)[car]
    cab = Boxes(
        center[car] - fwd * back,
        cab_half,
        np.stack([body_top[car], top[car]], 1),
        np.asarray(yaw, dtype=np.float64)[car].copy(),
        np.full(int(car.sum()), KIND_CAR, np.int8),
    )
    return Boxes.concat(body, cab)
