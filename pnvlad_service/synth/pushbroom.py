"""A run recorded with a push-broom line scanner, as the Oxford RobotCar's ``lms_front`` was.

:class:`PushbroomDrive` is a :class:`~pnvlad_service.synth.runs.SimulatedDrive` whose scans are
the scanner's lines, ``rate_hz`` of them a second while the vehicle drives (at 50 Hz and 9 m/s a
line every 0.18 m: the spacing along the street follows the run's speed). Each line is cast from
the scanner's true place on the vehicle (:func:`~pnvlad_service.synth.linescan.cast_line`) and
given in the vehicle's axes about the scanner (x forward, y left, z up); its pose, the one
``prepare_drive`` lays it with, is the run's *recorded* GNSS/INS pose of the scanner, whose
error drifts smoothly along the run (a random walk drawn every ``noise_knot_m`` metres, a cubic
spline between: an INS is smooth from line to line, its drift is not), so the accumulated
submaps smear as the real ones do. Everything else (route, lane, speed, traffic, parked cars,
season, roadworks) is the spinning sensors' run, drawn from the same streams.

Lines are cast a block at a time (``lines_per_scene`` lines, 0.1 s at 50 Hz) in one scene: the
traffic stands still within a block and moves between blocks. A block's random stream is drawn
from ``(seed, block)``, so a line is the same whichever order the lines are asked for in.
"""

from __future__ import annotations

import copy
from dataclasses import fields

import numpy as np

from pnvlad_service.synth.linescan import cast_line, line_fan, scene_near
from pnvlad_service.synth.runs import (
    Route,
    RunConditions,
    RunScene,
    SimulatedDrive,
    _level,
    _Movers,
    _smooth_walk,
)
from pnvlad_service.synth.sensors import PushbroomConfig
from pnvlad_service.synth.world import World


class PushbroomDrive(SimulatedDrive):
    """One run of the vehicle along ``route`` recorded by the line scanner ``lidar``: a
    :class:`pnvlad_service.data.drive.Drive` of lines (``scan(i)``: float32 [N, 3] metres in
    the vehicle's axes about the scanner; ``poses`` [T, 4, 4] scanner to UTM as recorded,
    ``true_poses`` as cast)."""

    lidar: PushbroomConfig  # type: ignore[assignment]

    def __init__(
        self,
        world: World,
        route: Route,
        name: str,
        *,
        seed: int,
        start_us: int,
        conditions: RunConditions | None = None,
        lidar: PushbroomConfig | None = None,
        lines_per_scene: int = 5,
        noise_knot_m: float = 20.0,
    ) -> None:
        self._block = max(1, int(lines_per_scene))
        self._knot = float(noise_knot_m)
        self._cache: dict[int, list[np.ndarray]] = {}
        self._segments: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        super().__init__(
            world,
            route,
            name,
            seed=seed,
            start_us=start_us,
            conditions=conditions,
            lidar=lidar or PushbroomConfig(),  # type: ignore[arg-type]
        )

    def _setup_sensor(self) -> None:
        self._fan = line_fan(self.lidar)

    def _spacing(self, scan_spacing: float) -> float:
        """A line every ``speed / rate_hz`` metres."""
        return self.speed / self.lidar.rate_hz

    @property
    def line_spacing(self) -> float:
        """Metres driven between two lines."""
        return self.speed / self.lidar.rate_hz

    def _place_sensor(self) -> None:
        """The scanner where the mounting puts it on the vehicle: its offset turned by the
        vehicle's attitude, about the road below the vehicle's reference point."""
        self.vehicle_xy = self.true_xy
        off = self.attitude @ self._fan.origin  # [T, 3]
        ground = self.world.ground.height(self.vehicle_xy[:, 0], self.vehicle_xy[:, 1])
        self.true_xy = self.vehicle_xy + off[:, :2]
        self.true_z = ground + off[:, 2]

    def _recorded_poses(self, rng: np.random.Generator, s: np.ndarray) -> np.ndarray:
        """The true poses with the GNSS/INS error: random walks in position and heading drawn
        every ``noise_knot_m`` of the run, a cubic spline through them at the lines."""
        cond = self.conditions
        knots = np.arange(0.0, (s[-1] if len(s) else 0.0) + self._knot, self._knot)
        corr = cond.noise_correlation_m
        walks = [
            _smooth_walk(rng, knots, std, corr)
            for std in (cond.position_noise / np.sqrt(2),) * 2
            + (np.deg2rad(cond.heading_noise_deg),)
        ]
        if len(knots) < 2:
            en, nn, yn = (np.full(len(s), w[0]) for w in walks)
        else:
            from scipy.interpolate import CubicSpline

            en, nn, yn = (CubicSpline(knots, w)(s) for w in walks)
        est_xy = self.true_xy + np.stack([en, nn], 1)
        return self._poses(_level(yn) @ self.attitude, est_xy)

    def scan(self, i: int, rings: bool = False) -> np.ndarray:
        """Line ``i``: float32 [N, 3] metres in the vehicle's axes about the scanner."""
        if not 0 <= i < len(self):
            raise IndexError(f"line {i} of {len(self)}")
        block = i // self._block
        if block not in self._cache:
            self._cache = {block: self._cast_block(block)}  # lines are read in order
        return self._cache[block][i - block * self._block]

    def _movers_near(self, xy: np.ndarray, reach: float) -> RunScene:
        """The run's scene with only the traffic and pedestrians of the streets that come
        within ``reach`` (plus the pavements' width) of ``xy``: a mover stays on its street,
        so the others cannot be in view, and placing them all every block costs most."""
        if self._segments is None:
            roads = self.world.roads
            self._segments = (
                np.concatenate([r.points[:-1] for r in roads]),
                np.concatenate([r.points[1:] for r in roads]),
                np.concatenate([np.full(len(r.points) - 1, i) for i, r in enumerate(roads)]),
            )
        a, b, road = self._segments
        ab = b - a
        t = np.clip(((xy - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(a + t[:, None] * ab - xy, axis=1)
        near = np.zeros(len(self.world.roads), bool)
        near[road[dist < reach + 25.0]] = True
        view = copy.copy(self.scene)
        view.cars = _subset(self.scene.cars, near[self.scene.cars.road])
        view.people = _subset(self.scene.people, near[self.scene.people.road])
        return view

    def _cast_block(self, block: int) -> list[np.ndarray]:
        """The lines of one block, cast in the scene at the block's middle line's time."""
        lines = range(block * self._block, min((block + 1) * self._block, len(self)))
        mid = lines[len(lines) // 2]
        reach = self.lidar.max_range + 5.0 + self._block * self.line_spacing
        # about the vehicle, whose footprint no other vehicle overlaps (ego_clearance)
        scene = self._movers_near(self.vehicle_xy[mid], reach + 5.0).scene_at(
            float(self.times[mid]), self.vehicle_xy[mid], reach + 5.0
        )
        scene = scene_near(scene, self.true_xy[mid], reach)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 3, block]))
        out = []
        for i in lines:
            pos = np.array([self.true_xy[i, 0], self.true_xy[i, 1], self.true_z[i]])
            out.append(
                cast_line(
                    scene, self.world.ground, pos, self.attitude[i], self.lidar, rng, self._fan
                )
            )
        return out


def _subset(m: _Movers, keep: np.ndarray) -> _Movers:
    """The movers ``keep`` (bool [M]) of ``m``."""
    parts = {f.name: getattr(m, f.name)[keep] for f in fields(m) if f.name != "shapes"}
    return _Movers(**parts, shapes=None if m.shapes is None else m.shapes.take(keep))
