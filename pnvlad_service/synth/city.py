"""Generating one area of the synthetic city: ground, street graph, then the static scene.

:func:`generate_world` builds a :class:`~pnvlad_service.synth.world.World` from a
:class:`~pnvlad_service.synth.world.WorldConfig` and a seed, step by step (ground, roads, the
scene along every street side, signs, park trees), each step drawing from a random stream of
``(seed, district)``: the same seed and config give the same arrays.
"""

from __future__ import annotations

import logging

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.synth.streets import Street, box_samples, normal
from pnvlad_service.synth.world import (
    DISTRICTS,
    KIND_BUILDING,
    KIND_CAR,
    KIND_CROWN,
    KIND_FENCE,
    KIND_KERB,
    KIND_POLE,
    KIND_SIGN,
    KIND_TRUNK,
    KIND_WALL,
    Boxes,
    Cylinders,
    DistrictStyle,
    Ellipsoids,
    Ground,
    Road,
    Scene,
    World,
    WorldConfig,
)

log = logging.getLogger(__name__)


def _rng(seed: int, *purpose: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, *purpose]))


def _stable_id(text: str) -> int:
    """A stable integer for a name (Python's hash() is salted per process)."""
    return int.from_bytes(text.encode("utf-8")[:8].ljust(8, b"\0"), "little") % (2**31)


def _make_ground(cfg: WorldConfig, rng: np.random.Generator) -> Ground:
    ang = rng.uniform(0, 2 * np.pi)
    gradient = cfg.ground_slope * rng.uniform(0.3, 1.0) * np.array([np.cos(ang), np.sin(ang)])
    k = 3
    wavelengths = rng.uniform(250.0, 700.0, k)
    dirs = rng.uniform(0, 2 * np.pi, k)
    wavevector = (2 * np.pi / wavelengths)[:, None] * np.stack([np.cos(dirs), np.sin(dirs)], 1)
    amplitude = cfg.ground_relief * rng.uniform(0.3, 1.0, k) / k
    return Ground(gradient, amplitude, wavevector, rng.uniform(0, 2 * np.pi, k))


def _add_hills(ground: Ground, amplitude: float, rng: np.random.Generator) -> Ground:
    """``ground`` with two hill waves 160-320 m long, each up to half ``amplitude`` metres."""
    k = 2
    wavelengths = rng.uniform(160.0, 320.0, k)
    dirs = rng.uniform(0, 2 * np.pi, k)
    wave = (2 * np.pi / wavelengths)[:, None] * np.stack([np.cos(dirs), np.sin(dirs)], 1)
    amp = amplitude * rng.uniform(0.5, 1.0, k) / k
    return Ground(
        ground.gradient,
        np.concatenate([ground.amplitude, amp]),
        np.concatenate([ground.wavevector, wave]),
        np.concatenate([ground.phase, rng.uniform(0, 2 * np.pi, k)]),
    )


def _connected(n: int, edges: list[tuple[int, int]]) -> bool:
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen = {0}
    stack = [0]
    while stack:
        u = stack.pop()
        for v in adj[u]:
            if v not in seen:
                seen.add(v)
                stack.append(v)
    return len(seen) == n


def _polyline(a: np.ndarray, b: np.ndarray, bend: float, step: float = 2.0) -> np.ndarray:
    """Straight or quadratic-Bezier street from a to b; ``bend`` is the control-point offset
    as a share of the length (0: straight)."""
    length = float(np.linalg.norm(b - a))
    n = max(int(np.ceil(length * (1 + abs(bend)) / step)), 2)
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    if bend == 0.0:
        return a + t * (b - a)
    d = (b - a) / length
    ctrl = (a + b) / 2 + np.array([-d[1], d[0]]) * bend * length
    return (1 - t) ** 2 * a + 2 * (1 - t) * t * ctrl + t**2 * b


def _make_roads(
    cfg: WorldConfig, style: DistrictStyle, rng: np.random.Generator
) -> tuple[np.ndarray, list[Road]]:
    w, h = cfg.size
    lo, hi = style.block_size
    xs = [0.0]
    while xs[-1] < w - lo:
        xs.append(xs[-1] + rng.uniform(lo, hi))
    ys = [0.0]
    while ys[-1] < h - lo:
        ys.append(ys[-1] + rng.uniform(lo, hi))
    nx, ny = len(xs), len(ys)
    nodes = np.array([[x, y] for y in ys for x in xs], dtype=np.float64)
    inner = np.ones(len(nodes), bool)
    inner[
        [j * nx + i for j in range(ny) for i in range(nx) if i in (0, nx - 1) or j in (0, ny - 1)]
    ] = False
    nodes[inner] += rng.uniform(-style.jitter, style.jitter, (int(inner.sum()), 2))

    def idx(i: int, j: int) -> int:
        return j * nx + i

    edges: list[tuple[int, int]] = []
    for j in range(ny):
        for i in range(nx):
            if i + 1 < nx:
                edges.append((idx(i, j), idx(i + 1, j)))
            if j + 1 < ny:
                edges.append((idx(i, j), idx(i, j + 1)))
    # Remove some inner streets (T junctions, longer blocks) while the graph stays connected.
    alive = np.ones(len(edges), bool)
    n_remove = int(style.removed_share * len(edges))
    removed = 0
    for e in rng.permutation(len(edges)):
        if removed >= n_remove:
            break
        a, b = edges[e]
        if not (inner[a] or inner[b]):
            continue  # keep the perimeter: the outer ring road is the loop
        alive[e] = False
        if _connected(len(nodes), [edges[k] for k in np.flatnonzero(alive)]):
            removed += 1
        else:
            alive[e] = True
    edges = [edges[k] for k in np.flatnonzero(alive)]
    # Diagonal streets across a few blocks (Y junctions of other angles).
    for j in range(ny - 1):
        for i in range(nx - 1):
            if rng.random() < style.diagonal_share:
                if rng.random() < 0.5:
                    edges.append((idx(i, j), idx(i + 1, j + 1)))
                else:
                    edges.append((idx(i + 1, j), idx(i, j + 1)))
    roads = []
    main_rows = {0, ny // 2}
    for a, b in edges:
        bend = rng.uniform(-0.18, 0.18) if rng.random() < style.curved_share else 0.0
        if not (inner[a] or inner[b]) and bend != 0.0:
            bend = 0.0  # the outer ring stays straight so the map keeps its extent
        pts = _polyline(nodes[a], nodes[b], bend)
        ja, jb = a // nx, b // nx
        main = ja == jb and ja in main_rows
        if style.main_columns and a % nx == b % nx and a % nx in (0, nx // 2):
            main = True
        roads.append(Road(pts, style.road_half_width[1 if main else 0], (a, b)))
    return nodes, roads


class _Occupancy:
    """A 1 m raster of used land (roads, buildings) for placement checks."""

    def __init__(self, cfg: WorldConfig, margin: float = 60.0) -> None:
        self.x0 = -margin
        self.y0 = -margin
        self.res = 1.0
        self.grid = np.zeros(
            (
                int((cfg.size[1] + 2 * margin) / self.res),
                int((cfg.size[0] + 2 * margin) / self.res),
            ),
            dtype=bool,
        )

    def cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = np.floor((pts[:, 0] - self.x0) / self.res).astype(np.int64)
        r = np.floor((pts[:, 1] - self.y0) / self.res).astype(np.int64)
        ok = (r >= 0) & (r < self.grid.shape[0]) & (c >= 0) & (c < self.grid.shape[1])
        return r, c, ok

    def free(self, pts: np.ndarray) -> bool:
        r, c, ok = self.cells(pts)
        return bool(ok.all()) and not bool(self.grid[r, c].any())

    def mark(self, pts: np.ndarray) -> None:
        r, c, ok = self.cells(pts)
        self.grid[r[ok], c[ok]] = True


class _Builder:
    """Collects primitives in lists, then freezes them into arrays."""

    def __init__(self) -> None:
        self.boxes: list[tuple[float, ...]] = []
        self.cyl: list[tuple[float, ...]] = []
        self.ell: list[tuple[float, ...]] = []

    def box(self, cx, cy, hx, hy, z0, z1, yaw, kind) -> None:
        self.boxes.append((cx, cy, hx, hy, z0, z1, yaw, kind))

    def cylinder(self, cx, cy, r, z0, z1, kind) -> None:
        self.cyl.append((cx, cy, r, z0, z1, kind))

    def ellipsoid(self, cx, cy, cz, rx, rz, density, kind) -> None:
        self.ell.append((cx, cy, cz, rx, rz, density, kind))

    def tree(self, rng: np.random.Generator, ground: Ground, x, y, crown: tuple[float, float]):
        z = float(ground.height(x, y))
        trunk_h = rng.uniform(1.8, 3.5)
        r = rng.uniform(*crown)
        rz = r * rng.uniform(0.8, 1.4)
        self.cylinder(x, y, rng.uniform(0.12, 0.3), z - 0.3, z + trunk_h + rz * 0.5, KIND_TRUNK)
        self.ellipsoid(x, y, z + trunk_h + rz * 0.9, r, rz, rng.uniform(0.55, 0.85), KIND_CROWN)

    def freeze(self) -> Scene:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 8)
        c = np.asarray(self.cyl, dtype=np.float64).reshape(-1, 6)
        e = np.asarray(self.ell, dtype=np.float64).reshape(-1, 7)
        return Scene(
            Boxes(
                b[:, 0:2].copy(),
                b[:, 2:4].copy(),
                b[:, 4:6].copy(),
                b[:, 6].copy(),
                b[:, 7].astype(np.int8),
            ),
            Cylinders(c[:, 0:2].copy(), c[:, 2].copy(), c[:, 3:5].copy(), c[:, 5].astype(np.int8)),
            Ellipsoids(
                e[:, 0:3].copy(),
                np.stack([e[:, 3], e[:, 3], e[:, 4]], 1),
                e[:, 5].copy(),
                e[:, 6].astype(np.int8),
            ),
        )


def _templates(style: DistrictStyle, rng: np.random.Generator) -> list[dict[str, float]]:
    out = []
    for _ in range(style.n_templates):
        t = {
            "w": rng.uniform(*style.width),
            "d": rng.uniform(*style.depth),
            "h": rng.uniform(*style.height),
            "wing": float(rng.random() < style.wing_share),
            "wing_w": rng.uniform(0.3, 0.5),
            "wing_d": rng.uniform(0.4, 0.9),
            "wing_h": rng.uniform(0.5, 1.0),
        }
        out.append(t)
    return out


class _Placer:
    """Places the static scene of one area along its roads, drawing from one random stream.

    Each method places one kind of object; :func:`generate_world` calls them in a fixed order,
    so the stream (and the scene) depends only on the seed and the config.
    """

    def __init__(
        self,
        cfg: WorldConfig,
        style: DistrictStyle,
        ground: Ground,
        nodes: np.ndarray,
        roads: list[Road],
        rng: np.random.Generator,
    ) -> None:
        from scipy.spatial import cKDTree

        self.cfg, self.style, self.ground, self.nodes, self.rng = cfg, style, ground, nodes, rng
        self.road_hw = np.concatenate([np.full(len(r.points), r.half_width) for r in roads])
        self.road_id = np.concatenate([np.full(len(r.points), i) for i, r in enumerate(roads)])
        self.tree = cKDTree(np.concatenate([r.points for r in roads]))
        self.occ = _Occupancy(cfg)
        # Roads and pavements are used land.
        for r in roads:
            for p0, p1 in zip(r.points[:-1], r.points[1:], strict=True):
                d = p1 - p0
                yaw = float(np.arctan2(d[1], d[0]))
                half = np.array([np.linalg.norm(d) / 2 + 0.5, r.half_width + 1.0])
                self.occ.mark(box_samples((p0 + p1) / 2, half, yaw, step=0.9))
        self.b = _Builder()
        self.templates = _templates(style, rng)
        self.parking: list[tuple[float, ...]] = []

    def clear_of_roads(self, pts: np.ndarray, margin: float, own: int | None = None) -> bool:
        dist, i = self.tree.query(pts)
        ok = dist > self.road_hw[i] + margin
        if own is not None:
            ok |= self.road_id[i] == own
        return bool(ok.all())

    def near_junction(self, p: np.ndarray, radius: float) -> bool:
        return bool((np.linalg.norm(self.nodes - p, axis=1) < radius).any())

    def _z(self, c: np.ndarray) -> float:
        return float(self.ground.height(c[0], c[1]))

    def _foot(self, c: np.ndarray, half: np.ndarray, yaw: float) -> float:
        """Where a building's box starts: half a metre under the ground at its centre, or, in
        hilly areas, under its lowest corner (so that no side floats above a slope)."""
        if self.cfg.detail.hills <= 0:
            return self._z(c) - 0.5
        corners = box_samples(c, half, yaw, step=max(float(half.max()), 1.0))
        return float(self.ground.height(corners[:, 0], corners[:, 1]).min()) - 0.5

    def side(self, street: Street, side: float) -> None:
        """Everything along one side of one street, in the order the stream is drawn."""
        rng, style = self.rng, self.style
        start = rng.uniform(0, 8)
        setback = rng.uniform(*style.setback)
        walled = rng.random() < style.wall_share
        self.buildings(street, side, start, setback)
        if walled and street.total > 40:
            self.wall(street, side)
        self.kerbs(street, side)
        if style.street_tree_spacing > 0:
            self.street_trees(street, side)
        self.poles(street, side)
        self.parking_slots(street, side)

    def buildings(self, street: Street, side: float, start: float, setback: float) -> None:
        """Buildings along the frontage (from the district's templates), wings and fences."""
        rng, total, hw = self.rng, street.total, street.half_width
        s = start
        while s < total - 5:
            tpl = self.templates[int(rng.integers(len(self.templates)))]
            w, d = tpl["w"], tpl["d"]
            hgt = tpl["h"] * rng.uniform(0.95, 1.05)
            p, t = street.at(min(s + w / 2, total))
            n = normal(t, side)
            c = p + n * (hw + setback + d / 2)
            yaw = float(np.arctan2(t[1], t[0]))
            samples = box_samples(c, np.array([w / 2, d / 2]) + 0.3, yaw, step=1.0)
            if self.occ.free(samples) and self.clear_of_roads(samples, 0.6):
                self.occ.mark(samples)
                z = self._z(c)
                foot = self._foot(c, np.array([w / 2, d / 2]), yaw)
                self.b.box(c[0], c[1], w / 2, d / 2, foot, z + hgt, yaw, KIND_BUILDING)
                if tpl["wing"]:
                    self.wing(tpl, c, n, t, w, d, hgt, yaw)
                if rng.random() < self.style.fence_share:
                    fc = p + n * (hw + setback * 0.5)
                    fz = self._z(fc)
                    top = fz + rng.uniform(0.9, 1.6)
                    self.b.box(fc[0], fc[1], w / 2 + 1.0, 0.04, fz - 0.2, top, yaw, KIND_FENCE)
            s += w + rng.uniform(*self.style.gap)

    def wing(
        self,
        tpl: dict[str, float],
        c: np.ndarray,
        n: np.ndarray,
        t: np.ndarray,
        w: float,
        d: float,
        hgt: float,
        yaw: float,
    ) -> None:
        """The L-shaped wing behind a building, where the land is free."""
        ww, wd = w * tpl["wing_w"], d * tpl["wing_d"]
        wc = c + n * (d / 2 + wd / 2) + t * (w / 2 - ww / 2)
        ws = box_samples(wc, np.array([ww / 2, wd / 2]) + 0.3, yaw, step=1.0)
        if self.occ.free(ws) and self.clear_of_roads(ws, 0.6):
            self.occ.mark(ws)
            z2 = self._z(wc)
            foot = self._foot(wc, np.array([ww / 2, wd / 2]), yaw)
            self.b.box(
                wc[0], wc[1], ww / 2, wd / 2, foot, z2 + hgt * tpl["wing_h"], yaw, KIND_BUILDING
            )

    def wall(self, street: Street, side: float) -> None:
        """A wall along a (campus) street side, in 8 m pieces where the land is free."""
        for s0 in np.arange(10.0, street.total - 10.0, 8.0):
            p, t = street.at(s0 + 4.0)
            c = p + normal(t, side) * (street.half_width + 2.5)
            if self.clear_of_roads(c[None], 1.5) and self.occ.free(c[None]):
                z = self._z(c)
                yaw = float(np.arctan2(t[1], t[0]))
                self.b.box(c[0], c[1], 4.0, 0.15, z - 0.2, z + 2.2, yaw, KIND_WALL)

    def kerbs(self, street: Street, side: float) -> None:
        """Kerb stones in 10 m pieces (4 m in hilly areas, to follow the slope), except near
        junctions."""
        piece = 4.0 if self.cfg.detail.hills > 0 else 10.0
        for s0 in np.arange(0.0, street.total, piece):
            p, t = street.at(min(s0 + piece / 2, street.total))
            c = p + normal(t, side) * (street.half_width + 0.1)
            if not self.near_junction(p, street.half_width + 10.0):
                z = self._z(c)
                yaw = float(np.arctan2(t[1], t[0]))
                self.b.box(c[0], c[1], piece / 2, 0.12, z - 0.1, z + 0.15, yaw, KIND_KERB)

    def street_trees(self, street: Street, side: float) -> None:
        """Trees on the pavement every ``street_tree_spacing`` metres, a share of them planted."""
        rng, style = self.rng, self.style
        for s0 in np.arange(rng.uniform(3, 10), street.total, style.street_tree_spacing):
            p, t = street.at(s0)
            if self.near_junction(p, 14.0) or rng.random() > style.street_tree_share:
                continue
            c = p + normal(t, side) * (street.half_width + 1.3)
            pad = box_samples(c, np.array([0.3, 0.3]), 0.0, 0.5)
            if self.occ.free(pad) or self.clear_of_roads(c[None], 0.8):
                self.b.tree(rng, self.ground, c[0], c[1], style.crown_radius)

    def poles(self, street: Street, side: float) -> None:
        """Lamp posts every ``pole_spacing`` metres, staggered between the two sides."""
        spacing = self.style.pole_spacing
        offset = 0.0 if side > 0 else spacing / 2
        for s0 in np.arange(offset + 5.0, street.total - 5.0, spacing):
            p, t = street.at(s0)
            c = p + normal(t, side) * (street.half_width + 0.6)
            if self.clear_of_roads(c[None], 0.3):
                z = self._z(c)
                self.b.cylinder(c[0], c[1], 0.1, z - 0.2, z + self.rng.uniform(6.0, 8.0), KIND_POLE)

    def parking_slots(self, street: Street, side: float) -> None:
        """Kerb-side parking slots every 6.5 m (a car or, one in ten, a van), away from
        junctions; each run decides which are taken."""
        rng = self.rng
        for s0 in np.arange(16.0, street.total - 16.0, 6.5):
            p, t = street.at(s0)
            if self.near_junction(p, 18.0):
                continue
            c = p + normal(t, side) * (street.half_width - 1.1)
            z = self._z(c)
            ln, ht = rng.uniform(4.0, 5.0), rng.uniform(1.4, 1.7)
            if rng.random() < 0.1:
                ln, ht = rng.uniform(5.0, 6.5), rng.uniform(2.1, 2.8)  # vans
            yaw = float(np.arctan2(t[1], t[0]))
            self.parking.append((c[0], c[1], ln / 2, 0.9, z, z + ht, yaw, KIND_CAR))

    def signs(self) -> None:
        """A sign on a pole near most junctions."""
        rng = self.rng
        for p in self.nodes:
            if rng.random() < 0.6:
                ang = rng.uniform(0, 2 * np.pi)
                c = p + 9.5 * np.array([np.cos(ang), np.sin(ang)])
                if self.clear_of_roads(c[None], 0.3):
                    z = self._z(c)
                    top = z + rng.uniform(2.4, 3.2)
                    self.b.cylinder(c[0], c[1], 0.05, z - 0.2, top, KIND_POLE)
                    self.b.box(c[0], c[1], 0.35, 0.03, top - 0.1, top + 0.6, ang, KIND_SIGN)

    def park_trees(self) -> None:
        """Park and garden trees at random places on free land."""
        w, h = self.cfg.size
        n_park = int(self.style.park_tree_density * w * h / 1000.0)
        cand = self.rng.uniform([0.0, 0.0], [w, h], (n_park, 2))
        for c in cand:
            pad = box_samples(c, np.array([1.0, 1.0]), 0.0, 1.0)
            if self.occ.free(pad):
                self.occ.mark(box_samples(c, np.array([0.5, 0.5]), 0.0, 1.0))
                self.b.tree(self.rng, self.ground, c[0], c[1], self.style.crown_radius)

    def slots(self) -> Boxes:
        """The parking slots placed so far, as boxes."""
        pk = np.asarray(self.parking, dtype=np.float64).reshape(-1, 8)
        return Boxes(
            pk[:, 0:2].copy(),
            pk[:, 2:4].copy(),
            pk[:, 4:6].copy(),
            pk[:, 6].copy(),
            pk[:, 7].astype(np.int8),
        )


def generate_world(config: WorldConfig | None = None, seed: int = 0) -> World:
    """Build one area of the city from ``config`` and ``seed`` (deterministic).

    Steps, each from its own random stream of ``(seed, district)``: the ground, the street
    graph, then the scene along every side of every street (buildings, walls, kerbs, street
    trees, poles, parking slots), signs at junctions and trees on the free land.
    """
    cfg = config or WorldConfig()
    if cfg.district not in DISTRICTS:
        raise InputError(
            f"unknown district {cfg.district!r}; choose one of {sorted(DISTRICTS)}", "district"
        )
    style = DISTRICTS[cfg.district]
    sid = _stable_id(cfg.district)
    ground = _make_ground(cfg, _rng(seed, sid, 1))
    if cfg.detail.hills > 0:  # from a stream of their own: the gentle ground stays as it was
        ground = _add_hills(ground, cfg.detail.hills, _rng(seed, sid, 5))
    nodes, roads = _make_roads(cfg, style, _rng(seed, sid, 2))
    placer = _Placer(cfg, style, ground, nodes, roads, _rng(seed, sid, 3))
    for r in roads:
        street = Street(r)
        for side in (1.0, -1.0):
            placer.side(street, side)
    placer.signs()
    placer.park_trees()
    detail = cfg.detail
    if detail.variety is not None:  # a stream of its own, before the detail that follows it
        from pnvlad_service.synth.variety import vary_city

        vary_city(placer, roads, detail.variety, _rng(seed, sid, 6))
    if detail.any:  # a stream of its own: the rest of the city stays where it was
        from pnvlad_service.synth.furniture import clumped_crowns, place_detail
        from pnvlad_service.synth.structures import place_structures

        detail_rng = _rng(seed, sid, 4)
        place_detail(placer, roads, detail, detail_rng)
        place_structures(placer, roads, detail, detail_rng)
    scene = placer.b.freeze()
    if detail.crown_clumps > 1:
        scene = clumped_crowns(scene, detail.crown_clumps, detail_rng)
    slots = placer.slots()
    log.debug(
        "world %s seed %d: %d roads, %d boxes, %d cylinders, %d crowns, %d parking slots",
        cfg.district,
        seed,
        len(roads),
        len(scene.boxes),
        len(scene.cylinders),
        len(scene.ellipsoids),
        len(slots),
    )
    return World(
        cfg, seed, ground, roads, nodes, scene, slots, (0.0, 0.0, cfg.size[0], cfg.size[1])
    )
