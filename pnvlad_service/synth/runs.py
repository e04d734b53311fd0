"""Runs through the synthetic city: a route, per-run conditions, and a simulated drive.

A run is the vehicle driving the area's route once. What differs between runs, each drawn from
``(seed, area, run)`` so that any run can be regenerated on its own:

- lane offset and speed;
- GNSS/INS pose noise: a smooth random walk of about a metre in position and a few tenths of a
  degree in heading, in the poses used to build the submaps (the LiDAR itself is cast from the
  true pose, so accumulated scans smear the way real ones do);
- traffic: cars moving along the streets and pedestrians on the pavements, positions a function
  of time, so that they smear across an accumulated window as real ones do;
- parked cars: which kerb-side slots are taken;
- season: tree crowns scaled (grow or shrink) and their foliage density changed;
- roadworks: cones and barriers added in a few places, and a few street objects removed there.

:class:`SimulatedDrive` implements :class:`pnvlad_service.data.drive.Drive`, so submaps are cut by
the same ``prepare_drive`` path a user's recorded drive takes; its sensor hooks
(``_setup_sensor``, ``_spacing``, ``_place_sensor``, ``scan``) are what
:class:`pnvlad_service.synth.pushbroom.PushbroomDrive` changes for a line scanner. World frame:
x = easting, y = northing, z = up, UTM metres; scans are in the sensor frame (x forward, y left,
z up).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from pnvlad_service.synth.lidar import LidarConfig, RayBundle, cast_scan, ray_bundle
from pnvlad_service.synth.vehicles import Shapes, draw_shapes, vehicle_boxes
from pnvlad_service.synth.world import (
    KIND_BARRIER,
    KIND_CAR,
    KIND_CONE,
    KIND_PEDESTRIAN,
    KIND_POLE,
    KIND_SIGN,
    KIND_TRUNK,
    Boxes,
    Cylinders,
    Ellipsoids,
    Scene,
    World,
)

log = logging.getLogger(__name__)


class RunConditions(BaseModel):
    """What changes from run to run; each value drawn per run from the range given."""

    lane_offset: float = Field(1.2, ge=0, description="largest offset from the lane centre, m")
    speed: tuple[float, float] = Field((6.0, 12.0), description="driving speed range, m/s")
    position_noise: float = Field(
        1.5, ge=0, description="std of the GNSS/INS position error (slow random walk), m"
    )
    heading_noise_deg: float = Field(
        0.8, ge=0, description="std of the INS heading error (slow random walk), degrees"
    )
    noise_correlation_m: float = Field(
        60.0, gt=0, description="distance over which the pose error decorrelates, m"
    )
    parked_share: tuple[float, float] = Field(
        (0.1, 0.9), description="range of the share of parking slots taken in a run"
    )
    traffic_per_km: float = Field(50.0, ge=0, description="moving vehicles per km of street")
    truck_share: float = Field(
        0.2, ge=0, le=1, description="share of moving vehicles that are buses or lorries"
    )
    pedestrians_per_km: float = Field(80.0, ge=0, description="pedestrians per km of street")
    reverse_share: float = Field(
        0.3, ge=0, le=1, description="chance that a run drives the route the other way round"
    )
    crown_scale: tuple[float, float] = Field(
        (0.7, 1.15), description="season: range of the tree-crown size factor of a run"
    )
    crown_density: tuple[float, float] = Field(
        (0.25, 1.0), description="season: range of the foliage density factor of a run"
    )
    roadworks_per_km: float = Field(3.0, ge=0, description="roadworks sites per km of route")
    removal_radius: float = Field(
        25.0,
        ge=0,
        description="street objects (poles, signs, trees) removed within this "
        "distance of a roadworks site, m",
    )
    ego_clearance: float | None = Field(
        None,
        ge=0,
        description="metres the vehicle keeps from parked cars' sides, and no moving vehicle "
        "overlaps it (None: the first benchmarks' lane, which could run through parked and "
        "oncoming cars)",
    )
    vehicle_shapes: bool = Field(
        False,
        description="cars as a body and a cabin of several shapes, vans as one tall box, "
        "parked ones changing shape from run to run (False: one box each)",
    )
    follow_ground: bool = Field(
        False,
        description="the vehicle, and its sensor, pitched and rolled by the slope it stands "
        "on, in the scans and the poses (False: the sensor level on any slope)",
    )


@dataclass
class Route:
    """The path every run follows: ``points`` float64 [K, 2] local metres about every 1 m,
    ``s`` float64 [K] travelled distance, ``half_width`` float64 [K] of the street there."""

    points: np.ndarray
    s: np.ndarray
    half_width: np.ndarray

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position [M, 2], unit tangent [M, 2] and street half width [M] at distances ``s``."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.s[-1])
        k = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2)
        seg = self.points[k + 1] - self.points[k]
        seglen = self.s[k + 1] - self.s[k]
        t = seg / np.maximum(seglen, 1e-9)[:, None]
        p = self.points[k] + t * (s - self.s[k])[:, None]
        return p, t, self.half_width[k]


def _resample(points: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline every ``step`` metres (first and last kept)."""
    d = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    keep = np.r_[True, np.diff(d) > 1e-9]
    points, d = points[keep], d[keep]
    s = np.arange(0.0, d[-1], step)
    s = np.r_[s, d[-1]] if d[-1] - s[-1] > 1e-6 else s
    return np.stack([np.interp(s, d, points[:, 0]), np.interp(s, d, points[:, 1])], 1)


def make_route(world: World, length_m: float, seed: int) -> Route:
    """A drive through the street network of about ``length_m`` metres.

    A walk over the junction graph that never turns straight back, prefers streets it has not
    driven yet and, among those, the one that goes on most straight (long stretches of similar
    road, as in the real benchmarks). Deterministic in ``(world, seed)``.
    """
    rng = np.random.default_rng(np.random.SeedSequence([world.seed, seed, 77]))
    adj: dict[int, list[int]] = {}
    for i, r in enumerate(world.roads):
        a, b = r.nodes
        adj.setdefault(a, []).append(i)
        adj.setdefault(b, []).append(i)
    # Start at the junction nearest the middle of the map, leave by a random street.
    mid = np.array(
        [(world.extent[0] + world.extent[2]) / 2, (world.extent[1] + world.extent[3]) / 2]
    )
    node = int(np.argmin(np.linalg.norm(world.nodes - mid, axis=1)))
    used = np.zeros(len(world.roads), dtype=np.int64)
    pieces: list[np.ndarray] = []
    widths: list[np.ndarray] = []
    total = 0.0
    heading: np.ndarray | None = None
    prev_road = -1
    while total < length_m:
        options = [i for i in adj[node] if i != prev_road] or adj[node]
        scores = []
        for i in options:
            r = world.roads[i]
            pts = r.points if r.nodes[0] == node else r.points[::-1]
            d = pts[min(3, len(pts) - 1)] - pts[0]
            d = d / max(np.linalg.norm(d), 1e-9)
            straight = 0.0 if heading is None else float(d @ heading)
            scores.append(-3.0 * used[i] + 1.0 * straight + rng.uniform(0.0, 1.2))
        i = options[int(np.argmax(scores))]
        r = world.roads[i]
        pts = r.points if r.nodes[0] == node else r.points[::-1]
        node = r.nodes[1] if r.nodes[0] == node else r.nodes[0]
        used[i] += 1
        prev_road = i
        d = pts[-1] - pts[-4 if len(pts) >= 4 else 0]
        heading = d / max(np.linalg.norm(d), 1e-9)
        pieces.append(pts if not pieces else pts[1:])
        widths.append(np.full(len(pieces[-1]), r.half_width))
        total += float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    raw = np.concatenate(pieces)
    hw_raw = np.concatenate(widths)
    pts = _resample(_smooth_corners(raw), 1.0)
    # Street width at each resampled point: that of the nearest raw point.
    from scipy.spatial import cKDTree

    hw = hw_raw[cKDTree(raw).query(pts)[1]]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    cut = int(np.searchsorted(s, length_m)) + 1
    return Route(pts[:cut], s[:cut], hw[:cut])


def _smooth_corners(points: np.ndarray, passes: int = 6) -> np.ndarray:
    """Round junction corners a little (a vehicle does not turn on the spot)."""
    p = _resample(points, 2.0)
    for _ in range(passes):
        q = p.copy()
        q[1:-1] = 0.25 * p[:-2] + 0.5 * p[1:-1] + 0.25 * p[2:]
        p = q
    return p


def _smooth_walk(rng: np.random.Generator, s: np.ndarray, std: float, corr: float) -> np.ndarray:
    """A stationary, smooth random process over distance ``s`` [T] with the given std and
    correlation length (an Ornstein-Uhlenbeck walk sampled at the scans)."""
    out = np.empty(len(s))
    if len(s) == 0:
        return out
    out[0] = rng.normal(0.0, std)
    for k in range(1, len(s)):
        a = np.exp(-(s[k] - s[k - 1]) / corr)
        out[k] = a * out[k - 1] + np.sqrt(1 - a * a) * rng.normal(0.0, std)
    return out


@dataclass
class _Movers:
    """Objects moving along the streets: road index, start distance, speed (m/s, signed),
    lateral offset from the centreline (m), size."""

    road: np.ndarray
    s0: np.ndarray
    v: np.ndarray
    lateral: np.ndarray
    half: np.ndarray  # [M, 2] cars; [M, 1] radius for pedestrians
    height: np.ndarray
    shapes: Shapes | None = None  # cars with RunConditions.vehicle_shapes


class RunScene:
    """The scene as one run sees it: the static city edited by the run's conditions, plus
    traffic that moves with time."""

    def __init__(
        self, world: World, conditions: RunConditions, route: Route, rng: np.random.Generator
    ):
        self.world = world
        self.conditions = conditions
        sc = world.scene
        cond = conditions
        # A stream of its own for what the first benchmarks did not draw (their runs unchanged).
        self._extra = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])
        parked = self._parked(rng)
        crowns = self._season(rng)
        # Roadworks: sites along the route; cones and barriers added, street furniture removed.
        n_sites = rng.poisson(cond.roadworks_per_km * route.length / 1000.0)
        site_s = rng.uniform(0.0, route.length, n_sites)
        site_p, site_t, site_hw = route.at(site_s)
        boxes = sc.boxes
        cyl = sc.cylinders
        keep_b = np.ones(len(boxes), bool)
        keep_c = np.ones(len(cyl), bool)
        keep_e = np.ones(len(crowns), bool)
        add_b: list[tuple[float, ...]] = []
        add_c: list[tuple[float, ...]] = []
        g = world.ground
        for p0, t0, hw in zip(site_p, site_t, site_hw, strict=True):
            if cond.removal_radius > 0:
                near_b = np.linalg.norm(boxes.center - p0, axis=1) < cond.removal_radius
                keep_b &= ~(near_b & (boxes.kind == KIND_SIGN))
                near_c = np.linalg.norm(cyl.center - p0, axis=1) < cond.removal_radius
                keep_c &= ~(near_c & np.isin(cyl.kind, (KIND_POLE, KIND_TRUNK)))
                near_e = np.linalg.norm(crowns.center[:, :2] - p0, axis=1) < cond.removal_radius
                keep_e &= ~near_e
            n = np.array([t0[1], -t0[0]]) * (1.0 if rng.random() < 0.5 else -1.0)
            yaw = float(np.arctan2(t0[1], t0[0]))
            length = rng.uniform(12.0, 30.0)
            for a in np.arange(-length / 2, length / 2, 2.5):
                c = p0 + t0 * a + n * (hw - 1.5)
                z = float(g.height(c[0], c[1]))
                add_c.append((c[0], c[1], 0.18, z, z + 0.75, KIND_CONE))
            c = p0 + n * (hw + 0.8)
            z = float(g.height(c[0], c[1]))
            add_b.append(
                (c[0], c[1], length / 2, 0.3, z, z + rng.uniform(1.0, 2.0), yaw, KIND_BARRIER)
            )
            if rng.random() < 0.5:  # a site container or skip
                c = p0 + n * (hw + 3.0) + t0 * rng.uniform(-5, 5)
                add_b.append((c[0], c[1], 3.0, 1.2, z, z + 2.6, yaw, KIND_BARRIER))
        ab = np.asarray(add_b, dtype=np.float64).reshape(-1, 8)
        ac = np.asarray(add_c, dtype=np.float64).reshape(-1, 6)
        self.boxes = Boxes.concat(
            boxes.take(keep_b),
            parked,
            Boxes(ab[:, 0:2], ab[:, 2:4], ab[:, 4:6], ab[:, 6], ab[:, 7].astype(np.int8)),
        )
        self.cylinders = Cylinders.concat(
            cyl.take(keep_c),
            Cylinders(ac[:, 0:2], ac[:, 2], ac[:, 3:5], ac[:, 5].astype(np.int8)),
        )
        self.crowns = crowns.take(keep_e)
        self.removed = int((~keep_b).sum() + (~keep_c).sum() + (~keep_e).sum())
        self.roadworks = route.at(site_s)[0]
        # Traffic and pedestrians on every street, moving with time.
        lengths = np.array(
            [float(np.linalg.norm(np.diff(r.points, axis=0), axis=1).sum()) for r in world.roads]
        )
        km = lengths.sum() / 1000.0
        self.cars = self._movers(rng, lengths, int(rng.poisson(cond.traffic_per_km * km)), car=True)
        self.people = self._movers(
            rng, lengths, int(rng.poisson(cond.pedestrians_per_km * km)), car=False
        )
        self._road_cum = [
            np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(r.points, axis=0), axis=1))]
            for r in world.roads
        ]

    def _season(self, rng: np.random.Generator) -> Ellipsoids:
        """The run's season: crowns grown or shrunk about their base, their foliage thinned."""
        el, cond = self.world.scene.ellipsoids, self.conditions
        scale = rng.uniform(*cond.crown_scale)
        dens = rng.uniform(*cond.crown_density)
        per_tree = rng.uniform(0.9, 1.1, len(el))
        radii = el.radii * (scale * per_tree)[:, None]
        center = el.center.copy()
        center[:, 2] = el.center[:, 2] - el.radii[:, 2] + radii[:, 2]  # crowns keep their base
        return Ellipsoids(center, radii, np.clip(el.density * dens, 0.05, 1.0), el.kind)

    def _parked(self, rng: np.random.Generator) -> Boxes:
        """The parked cars of this run: a share of the slots (and with ``vehicle_shapes``
        another car's shape in each slot, drawn from the run's extra stream)."""
        share = rng.uniform(*self.conditions.parked_share)
        p = self.world.parking
        taken = rng.random(len(p)) < share
        parked = Boxes(p.center[taken], p.half[taken], p.z[taken], p.yaw[taken], p.kind[taken])
        if not self.conditions.vehicle_shapes:
            return parked
        shapes = draw_shapes(self._extra, len(parked))
        return vehicle_boxes(parked.center, parked.yaw, parked.z[:, 0], shapes)

    def _movers(self, rng: np.random.Generator, lengths: np.ndarray, n: int, car: bool) -> _Movers:
        road = rng.choice(len(lengths), size=n, p=lengths / lengths.sum())
        hw = np.array([self.world.roads[i].half_width for i in road])
        side = np.where(rng.random(n) < 0.5, 1.0, -1.0)
        shapes = None
        if car:
            lateral = side * hw * rng.uniform(0.2, 0.45, n)
            v = -side * rng.uniform(5.0, 14.0, n)  # drive on the side of the direction
            half = np.stack([rng.uniform(2.0, 2.6, n), rng.uniform(0.85, 1.0, n)], 1)
            height = rng.uniform(1.4, 1.9, n)
            big = rng.random(n) < self.conditions.truck_share  # buses and lorries occlude most
            half[big, 0] = rng.uniform(4.0, 6.0, int(big.sum()))
            half[big, 1] = 1.25
            height[big] = rng.uniform(3.0, 3.8, int(big.sum()))
            if self.conditions.vehicle_shapes:  # buses and lorries stay one box
                shapes = draw_shapes(self._extra, n)
                shapes.half[big], shapes.height[big], shapes.cabin[big] = half[big], height[big], 0
        else:
            lateral = side * (hw + rng.uniform(0.8, 2.5, n))
            v = rng.choice([-1.0, 1.0], n) * rng.uniform(0.8, 1.6, n)
            half = rng.uniform(0.22, 0.3, (n, 1))
            height = rng.uniform(1.55, 1.9, n)
        return _Movers(road, rng.uniform(0.0, lengths[road]), v, lateral, half, height, shapes)

    def _place(self, m: _Movers, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Centres [M, 2] and yaw [M] of movers at time ``t`` seconds (they bounce at ends)."""
        centers = np.empty((len(m.road), 2))
        yaws = np.empty(len(m.road))
        for i in np.unique(m.road):
            sel = np.flatnonzero(m.road == i)
            pts = self.world.roads[i].points
            cum = self._road_cum[i]
            length = cum[-1]
            s = np.abs(np.mod(m.s0[sel] + m.v[sel] * t, 2 * length) - length)  # ping-pong
            x = np.interp(s, cum, pts[:, 0])
            y = np.interp(s, cum, pts[:, 1])
            k = np.clip(np.searchsorted(cum, s) - 1, 0, len(pts) - 2)
            d = pts[k + 1] - pts[k]
            d = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
            nrm = np.stack([d[:, 1], -d[:, 0]], 1)
            centers[sel] = np.stack([x, y], 1) + nrm * m.lateral[sel, None]
            yaws[sel] = np.arctan2(d[:, 1], d[:, 0])
        return centers, yaws

    def scene_at(self, t: float, near: np.ndarray, radius: float) -> Scene:
        """The scene at time ``t`` (s), with movers limited to those within ``radius`` of
        ``near`` (local metres [2]) to keep ray casting cheap."""
        boxes = self.boxes
        cyl = self.cylinders
        if len(self.cars.road):
            sel, c, yaw, z = self._near(self.cars, t, near, radius)
            if self.conditions.ego_clearance is not None:  # none where the vehicle itself is
                clear = _clear_of(c, yaw, self.cars.half[sel], near, self.conditions.ego_clearance)
                sel[np.flatnonzero(sel)[~clear]] = False
                c, yaw, z = c[clear], yaw[clear], z[clear]
            if self.cars.shapes is not None:
                part = self.cars.shapes.take(sel)
                boxes = Boxes.concat(boxes, vehicle_boxes(c, yaw, z[:, 0], part))
            else:
                kind = np.full(len(c), KIND_CAR, np.int8)
                boxes = Boxes.concat(boxes, Boxes(c, self.cars.half[sel], z, yaw, kind))
        if len(self.people.road):
            sel, c, _, z = self._near(self.people, t, near, radius)
            kind = np.full(len(c), KIND_PEDESTRIAN, np.int8)
            cyl = Cylinders.concat(cyl, Cylinders(c, self.people.half[sel, 0], z, kind))
        return Scene(boxes, cyl, self.crowns)

    def _near(
        self, m: _Movers, t: float, near: np.ndarray, radius: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The movers of ``m`` within ``radius`` of ``near`` at time ``t``: their mask [M],
        centres [K, 2], yaw [K] and bottom/top z [K, 2] (standing on the ground)."""
        c, yaw = self._place(m, t)
        sel = np.linalg.norm(c - near, axis=1) < radius
        z = self.world.ground.height(c[sel, 0], c[sel, 1])
        return sel, c[sel], yaw[sel], np.stack([z, z + m.height[sel]], 1)


#: Half length and half width of the vehicle that carries the sensor, metres.
EGO_HALF = (2.4, 0.95)


def _level(yaw: np.ndarray) -> np.ndarray:
    """float64 [T, 3, 3]: level orientations turned by ``yaw`` [T] radians about up."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros((len(yaw), 3, 3))
    out[:, 0, 0], out[:, 0, 1] = c, -s
    out[:, 1, 0], out[:, 1, 1] = s, c
    out[:, 2, 2] = 1.0
    return out


def ground_attitude(world: World, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """float64 [T, 3, 3]: a vehicle's orientation at ``xy`` [T, 2] heading ``yaw`` [T] on the
    ground's slope: up along the ground's normal, forward the heading laid onto the ground."""
    _, gx, gy = world.ground.height_and_grad(xy[:, 0], xy[:, 1])
    up = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    head = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], 1)
    fwd = head - (head * up).sum(1, keepdims=True) * up
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    return np.stack([fwd, np.cross(up, fwd), up], axis=2)


def _clear_of(
    centers: np.ndarray, yaw: np.ndarray, half: np.ndarray, ego: np.ndarray, margin: float
) -> np.ndarray:
    """Which vehicles (centres [M, 2], headings [M], half sizes [M, 2]) stay clear of the ego
    vehicle at ``ego`` [2] by ``margin`` metres (taken as parallel to each: a lane's view)."""
    rel = np.asarray(ego, dtype=np.float64)[:2] - centers
    c, s = np.cos(yaw), np.sin(yaw)
    along = np.abs(c * rel[:, 0] + s * rel[:, 1])
    across = np.abs(-s * rel[:, 0] + c * rel[:, 1])
    return (along > half[:, 0] + EGO_HALF[0] + margin) | (
        across > half[:, 1] + EGO_HALF[1] + margin
    )


class SimulatedDrive:
    """One run of the vehicle along ``route``: a :class:`pnvlad_service.data.drive.Drive`.

    ``timestamps`` int64 [T] µs from ``start_us``; ``poses`` float64 [T, 4, 4] sensor→UTM world
    *with* the run's GNSS/INS error; :meth:`scan` ray-casts the LiDAR from the *true* pose
    (deterministic per scan index, whatever the order scans are asked for).
    """

    def __init__(
        self,
        world: World,
        route: Route,
        name: str,
        *,
        seed: int,
        start_us: int,
        conditions: RunConditions | None = None,
        lidar: LidarConfig | None = None,
        scan_spacing: float = 2.0,
    ) -> None:
        self.world = world
        self.name = name
        self.seed = seed
        self.conditions = cond = conditions or RunConditions()
        self.lidar = lidar or LidarConfig()
        self._setup_sensor()
        rng = np.random.default_rng(np.random.SeedSequence([seed, 1]))
        self.speed = float(rng.uniform(*cond.speed))
        self.lane = float(rng.uniform(-cond.lane_offset, cond.lane_offset))
        self.reverse = bool(rng.random() < cond.reverse_share)
        s = np.arange(0.0, route.length, self._spacing(scan_spacing))
        p, t, hw = route.at(route.length - s if self.reverse else s)
        if self.reverse:
            t = -t
        nrm = np.stack([t[:, 1], -t[:, 0]], 1)
        # Keep to the right half of the street, about its lane centre, plus the run's offset.
        lateral = hw * 0.45 + self.lane
        if cond.ego_clearance is not None:  # out of the parking lane (kerb - 2.0 m .. kerb)
            lateral = np.clip(lateral, 0.5, hw - 2.0 - EGO_HALF[1] - cond.ego_clearance)
        true_xy = p + nrm * lateral[:, None]
        yaw = np.arctan2(t[:, 1], t[:, 0])
        self.true_xy = true_xy
        self.true_yaw = yaw
        # rad/s: the turn during a sweep, for sensors that do not de-skew
        self._yaw_rate = (
            np.gradient(np.unwrap(yaw), s) * self.speed if len(s) > 1 else np.zeros(len(s))
        )
        self.times = s / self.speed  # seconds since the start of the run
        self.timestamps = (start_us + np.round(self.times * 1e6)).astype(np.int64)
        # The sensor's orientation (sensor axes in the world): level, or on the ground's slope.
        self.attitude = ground_attitude(world, true_xy, yaw) if cond.follow_ground else _level(yaw)
        self._place_sensor()
        self.poses = self._recorded_poses(rng, s)
        self.scene = RunScene(
            world, cond, route, np.random.default_rng(np.random.SeedSequence([seed, 2]))
        )

    def _setup_sensor(self) -> None:
        """What the sensor needs once a run (a spinning sensor: its rays)."""
        self._rays: RayBundle = ray_bundle(self.lidar)

    def _spacing(self, scan_spacing: float) -> float:
        """Metres driven between two scans (``self.speed`` is drawn): the preset's."""
        return scan_spacing

    def _place_sensor(self) -> None:
        """The sensor's height ``true_z`` [T] above the vehicle's ``true_xy`` (a spinning
        sensor: ``mount_height`` above the ground there, whatever the slope)."""
        xy = self.true_xy
        self.true_z = self.world.ground.height(xy[:, 0], xy[:, 1]) + self.lidar.mount_height

    def _recorded_poses(self, rng: np.random.Generator, s: np.ndarray) -> np.ndarray:
        """float64 [T, 4, 4] sensor→UTM world as the GNSS/INS records them: the true poses
        with its error, smooth random walks over the distance ``s`` in position and heading."""
        cond = self.conditions
        en = _smooth_walk(rng, s, cond.position_noise / np.sqrt(2), cond.noise_correlation_m)
        nn = _smooth_walk(rng, s, cond.position_noise / np.sqrt(2), cond.noise_correlation_m)
        yn = _smooth_walk(rng, s, np.deg2rad(cond.heading_noise_deg), cond.noise_correlation_m)
        est_xy = self.true_xy + np.stack([en, nn], 1)
        # the heading error turns about up
        if cond.follow_ground:
            return self._poses(_level(yn) @ self.attitude, est_xy)
        return self._poses(_level(self.true_yaw + yn), est_xy)

    def _poses(self, rotation: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """float64 [T, 4, 4] sensor→UTM world of orientations ``rotation`` [T, 3, 3] at local
        ``xy`` [T, 2], the sensor at its true height."""
        poses = np.zeros((len(xy), 4, 4))
        poses[:, :3, :3] = rotation
        poses[:, :2, 3] = self.world.origin + xy  # UTM easting, northing
        poses[:, 2, 3] = self.true_z
        poses[:, 3, 3] = 1.0
        return poses

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def true_poses(self) -> np.ndarray:
        """float64 [T, 4, 4] sensor→UTM world as the scans were really cast (no GNSS/INS
        error); ``prepare_drive`` records from it each submap's true frame pose."""
        return self._poses(self.attitude, self.true_xy)

    def scan(self, i: int, rings: bool = False) -> Any:
        """Points float32 [N, 3] of scan ``i`` in the sensor frame, metres (with ``rings``, and
        each point's beam, 0 the top one)."""
        pos = np.array([self.true_xy[i, 0], self.true_xy[i, 1], self.true_z[i]])
        scene = self.scene.scene_at(float(self.times[i]), pos[:2], self.lidar.max_range + 10.0)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 3, i]))
        motion = (self.speed, float(self._yaw_rate[i]))
        return cast_scan(
            scene,
            self.world.ground,
            pos,
            float(self.true_yaw[i]),
            self.lidar,
            rng,
            self._rays,
            motion,
            rings,
            self.attitude[i] if self.conditions.follow_ground else None,
        )
