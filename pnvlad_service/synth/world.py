"""A seeded procedural city: roads, blocks, buildings, trees, poles, walls, parked-car slots.

Everything here is static: what every run of the vehicle sees the same way. Per-run changes
(parked cars, vegetation, roadworks, traffic) live in :mod:`pnvlad_service.synth.runs`.

Frames and units: the world is built in a *local* frame in float64 metres, x = easting,
y = northing, z = up, with the UTM position of the local origin in :attr:`World.origin`
(easting, northing), e.g. (620000, 5735000). Keeping geometry local keeps ray casting exact;
positions leave this module as UTM only through :meth:`World.to_utm`.

The scene is made of three analytic primitive kinds, cheap to ray-cast in bulk:

- oriented boxes (yaw only): buildings, walls, fences, kerbs, parked cars, sign plates;
- vertical cylinders: tree trunks, poles, pedestrians, cones;
- ellipsoids with a foliage density (share of rays that return): tree crowns;

plus a smooth height-field ground (gentle slopes). Same seed and config, same arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

log = logging.getLogger(__name__)

District = Literal["business", "residential", "campus"]

# Kinds, stored as int8 next to each primitive (used by runs.py for per-run edits and by
# preview.py for colours).
KIND_BUILDING, KIND_WALL, KIND_FENCE, KIND_KERB, KIND_CAR, KIND_SIGN = 0, 1, 2, 3, 4, 5
KIND_TRUNK, KIND_POLE, KIND_PEDESTRIAN, KIND_CONE, KIND_CROWN, KIND_BARRIER = 6, 7, 8, 9, 10, 11


class DistrictStyle(BaseModel):
    """How a district looks: street grid, building templates, vegetation, furniture."""

    block_size: tuple[float, float] = Field(description="street spacing range, metres")
    jitter: float = Field(12.0, description="junction position jitter, metres")
    curved_share: float = Field(0.25, description="share of streets drawn as curves")
    removed_share: float = Field(0.15, description="share of inner streets removed (T junctions)")
    diagonal_share: float = Field(0.08, description="share of blocks crossed by a diagonal street")
    road_half_width: tuple[float, float] = Field((4.0, 7.0), description="side, main; metres")
    n_templates: int = Field(4, description="building templates per district (repetition)")
    width: tuple[float, float] = Field(description="building frontage range, metres")
    depth: tuple[float, float] = Field(description="building depth range, metres")
    height: tuple[float, float] = Field(description="building height range, metres")
    wing_share: float = Field(0.3, description="share of templates with an L-shaped wing")
    setback: tuple[float, float] = Field(description="building distance from the kerb, metres")
    gap: tuple[float, float] = Field(description="gap between neighbouring buildings, metres")
    street_tree_spacing: float = Field(description="metres between street trees (0: none)")
    street_tree_share: float = Field(0.6, description="share of street-tree slots planted")
    park_tree_density: float = Field(description="trees per 1000 m² of free land")
    crown_radius: tuple[float, float] = Field((1.8, 3.5), description="metres")
    pole_spacing: float = Field(32.0, description="metres between lamp posts")
    fence_share: float = Field(0.0, description="share of buildings with a front fence")
    wall_share: float = Field(0.0, description="share of street sides lined with a wall")
    parking_share: float = Field(0.5, description="share of kerb slots with a parked car")


DISTRICTS: dict[str, DistrictStyle] = {
    # Dense business district: continuous tall frontage, few trees, deep street canyons.
    "business": DistrictStyle(
        block_size=(95.0, 130.0),
        road_half_width=(5.0, 8.0),
        n_templates=4,
        width=(18.0, 36.0),
        depth=(16.0, 30.0),
        height=(14.0, 40.0),
        setback=(2.0, 3.5),
        gap=(0.0, 2.0),
        street_tree_spacing=24.0,
        street_tree_share=0.4,
        park_tree_density=0.3,
        pole_spacing=28.0,
        parking_share=0.6,
    ),
    # Residential: low houses of three templates, gardens with many trees, front fences.
    "residential": DistrictStyle(
        block_size=(80.0, 115.0),
        road_half_width=(3.5, 5.5),
        n_templates=3,
        width=(8.0, 13.0),
        depth=(8.0, 12.0),
        height=(5.0, 8.5),
        wing_share=0.4,
        setback=(5.0, 9.0),
        gap=(4.0, 9.0),
        street_tree_spacing=14.0,
        street_tree_share=0.7,
        park_tree_density=2.5,
        crown_radius=(1.5, 3.2),
        pole_spacing=36.0,
        fence_share=0.6,
        parking_share=0.45,
    ),
    # Campus: large buildings set far back on lawns, tree-lined paths, walls.
    "campus": DistrictStyle(
        block_size=(140.0, 190.0),
        curved_share=0.35,
        road_half_width=(3.5, 6.0),
        n_templates=4,
        width=(28.0, 60.0),
        depth=(14.0, 28.0),
        height=(8.0, 20.0),
        wing_share=0.5,
        setback=(10.0, 24.0),
        gap=(15.0, 35.0),
        street_tree_spacing=16.0,
        street_tree_share=0.8,
        park_tree_density=1.6,
        crown_radius=(2.0, 4.0),
        pole_spacing=30.0,
        wall_share=0.2,
        parking_share=0.25,
    ),
}


class WorldConfig(BaseModel):
    """Size, district and georeference of one generated area."""

    district: str = Field("business", description="one of DISTRICTS")
    size: tuple[float, float] = Field((900.0, 700.0), description="extent x, y in metres")
    origin: tuple[float, float] = Field(
        (620000.0, 5735000.0), description="UTM easting, northing of the local origin, metres"
    )
    ground_slope: float = Field(0.015, description="largest mean ground gradient (1.5 %)")
    ground_relief: float = Field(2.5, description="amplitude of ground undulation, metres")


@dataclass
class Boxes:
    """Oriented boxes. center [N,2], half [N,2] (half length, half width), z [N,2] bottom/top,
    yaw [N] radians (rotation of the box's x axis from east), kind int8 [N]. Metres, local."""

    center: np.ndarray
    half: np.ndarray
    z: np.ndarray
    yaw: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)


@dataclass
class Cylinders:
    """Vertical cylinders. center [N,2], radius [N], z [N,2], kind int8 [N]. Metres, local."""

    center: np.ndarray
    radius: np.ndarray
    z: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)


@dataclass
class Ellipsoids:
    """Axis-aligned ellipsoids. center [N,3], radii [N,3], density [N] in (0, 1] (share of
    rays that return from the crown), kind int8 [N]. Metres, local."""

    center: np.ndarray
    radii: np.ndarray
    density: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)


@dataclass
class Scene:
    """Everything a ray can hit, apart from the ground."""

    boxes: Boxes
    cylinders: Cylinders
    ellipsoids: Ellipsoids


@dataclass
class Ground:
    """Height field z = h(x, y): a plane plus a few long sinusoids (local metres)."""

    gradient: np.ndarray  # float64 [2]
    amplitude: np.ndarray  # float64 [K]
    wavevector: np.ndarray  # float64 [K, 2], radians per metre
    phase: np.ndarray  # float64 [K]

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (metres) at local x, y (any matching shapes)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        h = self.gradient[0] * x + self.gradient[1] * y
        for a, k, p in zip(self.amplitude, self.wavevector, self.phase, strict=True):
            h = h + a * np.sin(k[0] * x + k[1] * y + p)
        return h

    def height_and_grad(
        self, x: np.ndarray, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height and its x, y derivatives at local x, y."""
        h = self.gradient[0] * x + self.gradient[1] * y
        gx = np.full_like(h, self.gradient[0])
        gy = np.full_like(h, self.gradient[1])
        for a, k, p in zip(self.amplitude, self.wavevector, self.phase, strict=True):
            arg = k[0] * x + k[1] * y + p
            h = h + a * np.sin(arg)
            c = a * np.cos(arg)
            gx = gx + c * k[0]
            gy = gy + c * k[1]
        return h, gx, gy


@dataclass
class Road:
    """A street: centreline float64 [K,2] sampled about every 2 m, half width in metres."""

    points: np.ndarray
    half_width: float
    nodes: tuple[int, int]


@dataclass
class World:
    """A generated area: roads, junction graph, static scene, ground and parking slots."""

    config: WorldConfig
    seed: int
    ground: Ground
    roads: list[Road]
    nodes: np.ndarray  # float64 [V, 2] junction positions
    scene: Scene
    parking: Boxes  # every kerb-side parking slot (a car each); runs choose which are taken
    extent: tuple[float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0))

    @property
    def origin(self) -> np.ndarray:
        """UTM (easting, northing) of the local origin, float64 [2]."""
        return np.asarray(self.config.origin, dtype=np.float64)

    def to_utm(self, xy: np.ndarray) -> np.ndarray:
        """Local x, y [..., 2] → UTM easting, northing [..., 2] (float64 metres)."""
        return np.asarray(xy, dtype=np.float64) + self.origin


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


def _box_samples(center: np.ndarray, half: np.ndarray, yaw: float, step: float = 0.8) -> np.ndarray:
    """Points covering an oriented rectangle (including its border), float64 [M,2]."""
    u = np.arange(-half[0], half[0] + 1e-9, step)
    v = np.arange(-half[1], half[1] + 1e-9, step)
    u = np.append(u, half[0])
    v = np.append(v, half[1])
    uu, vv = np.meshgrid(u, v)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([center[0] + c * uu - s * vv, center[1] + s * uu + c * vv], -1).reshape(-1, 2)


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


def generate_world(config: WorldConfig | None = None, seed: int = 0) -> World:
    """Build one area of the city from ``config`` and ``seed`` (deterministic)."""
    from scipy.spatial import cKDTree

    cfg = config or WorldConfig()
    if cfg.district not in DISTRICTS:
        from pnvlad_service.errors import InputError

        raise InputError(
            f"unknown district {cfg.district!r}; choose one of {sorted(DISTRICTS)}", "district"
        )
    style = DISTRICTS[cfg.district]
    sid = _stable_id(cfg.district)
    ground = _make_ground(cfg, _rng(seed, sid, 1))
    nodes, roads = _make_roads(cfg, style, _rng(seed, sid, 2))
    rng = _rng(seed, sid, 3)

    road_pts = np.concatenate([r.points for r in roads])
    road_hw = np.concatenate([np.full(len(r.points), r.half_width) for r in roads])
    road_id = np.concatenate([np.full(len(r.points), i) for i, r in enumerate(roads)])
    tree = cKDTree(road_pts)
    occ = _Occupancy(cfg)
    # Roads and pavements are used land.
    for r in roads:
        for p0, p1 in zip(r.points[:-1], r.points[1:], strict=True):
            d = p1 - p0
            yaw = float(np.arctan2(d[1], d[0]))
            half = np.array([np.linalg.norm(d) / 2 + 0.5, r.half_width + 1.0])
            occ.mark(_box_samples((p0 + p1) / 2, half, yaw, step=0.9))

    def clear_of_roads(pts: np.ndarray, margin: float, own: int | None = None) -> bool:
        dist, i = tree.query(pts)
        ok = dist > road_hw[i] + margin
        if own is not None:
            ok |= road_id[i] == own
        return bool(ok.all())

    def near_junction(p: np.ndarray, radius: float) -> bool:
        return bool((np.linalg.norm(nodes - p, axis=1) < radius).any())

    b = _Builder()
    templates = _templates(style, rng)
    parking: list[tuple[float, ...]] = []

    for r in roads:
        pts = r.points
        seg = np.diff(pts, axis=0)
        seglen = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seglen)])
        total = cum[-1]

        def at(s: float, pts=pts, seg=seg, seglen=seglen, cum=cum) -> tuple[np.ndarray, np.ndarray]:
            k = int(np.clip(np.searchsorted(cum, s) - 1, 0, len(seg) - 1))
            t = seg[k] / seglen[k]
            return pts[k] + t * (s - cum[k]), t

        for side in (1.0, -1.0):
            # Buildings along the frontage.
            s = rng.uniform(0, 8)
            setback = rng.uniform(*style.setback)
            walled = rng.random() < style.wall_share
            while s < total - 5:
                tpl = templates[int(rng.integers(len(templates)))]
                w, d = tpl["w"], tpl["d"]
                hgt = tpl["h"] * rng.uniform(0.95, 1.05)
                p, t = at(min(s + w / 2, total))
                n = np.array([t[1], -t[0]]) * side
                c = p + n * (r.half_width + setback + d / 2)
                yaw = float(np.arctan2(t[1], t[0]))
                half = np.array([w / 2, d / 2])
                samples = _box_samples(c, half + 0.3, yaw, step=1.0)
                if occ.free(samples) and clear_of_roads(samples, 0.6):
                    occ.mark(samples)
                    z = float(ground.height(c[0], c[1]))
                    b.box(c[0], c[1], w / 2, d / 2, z - 0.5, z + hgt, yaw, KIND_BUILDING)
                    if tpl["wing"]:
                        ww, wd = w * tpl["wing_w"], d * tpl["wing_d"]
                        wc = c + n * (d / 2 + wd / 2) + t * (w / 2 - ww / 2)
                        ws = _box_samples(wc, np.array([ww / 2, wd / 2]) + 0.3, yaw, step=1.0)
                        if occ.free(ws) and clear_of_roads(ws, 0.6):
                            occ.mark(ws)
                            z2 = float(ground.height(wc[0], wc[1]))
                            b.box(
                                wc[0],
                                wc[1],
                                ww / 2,
                                wd / 2,
                                z2 - 0.5,
                                z2 + hgt * tpl["wing_h"],
                                yaw,
                                KIND_BUILDING,
                            )
                    if rng.random() < style.fence_share:
                        fc = p + n * (r.half_width + setback * 0.5)
                        fz = float(ground.height(fc[0], fc[1]))
                        b.box(
                            fc[0],
                            fc[1],
                            w / 2 + 1.0,
                            0.04,
                            fz - 0.2,
                            fz + rng.uniform(0.9, 1.6),
                            yaw,
                            KIND_FENCE,
                        )
                s += w + rng.uniform(*style.gap)
            # Wall along a campus street side.
            if walled and total > 40:
                for s0 in np.arange(10.0, total - 10.0, 8.0):
                    p, t = at(s0 + 4.0)
                    n = np.array([t[1], -t[0]]) * side
                    c = p + n * (r.half_width + 2.5)
                    if clear_of_roads(c[None], 1.5) and occ.free(c[None]):
                        z = float(ground.height(c[0], c[1]))
                        b.box(
                            c[0],
                            c[1],
                            4.0,
                            0.15,
                            z - 0.2,
                            z + 2.2,
                            float(np.arctan2(t[1], t[0])),
                            KIND_WALL,
                        )
            # Kerbs, street trees, lamp posts, parking slots.
            for s0 in np.arange(0.0, total, 10.0):
                p, t = at(min(s0 + 5.0, total))
                n = np.array([t[1], -t[0]]) * side
                c = p + n * (r.half_width + 0.1)
                if not near_junction(p, r.half_width + 10.0):
                    z = float(ground.height(c[0], c[1]))
                    b.box(
                        c[0],
                        c[1],
                        5.0,
                        0.12,
                        z - 0.1,
                        z + 0.15,
                        float(np.arctan2(t[1], t[0])),
                        KIND_KERB,
                    )
            if style.street_tree_spacing > 0:
                for s0 in np.arange(rng.uniform(3, 10), total, style.street_tree_spacing):
                    p, t = at(s0)
                    if near_junction(p, 14.0) or rng.random() > style.street_tree_share:
                        continue
                    n = np.array([t[1], -t[0]]) * side
                    c = p + n * (r.half_width + 1.3)
                    if occ.free(_box_samples(c, np.array([0.3, 0.3]), 0.0, 0.5)) or clear_of_roads(
                        c[None], 0.8
                    ):
                        b.tree(rng, ground, c[0], c[1], style.crown_radius)
            offset = 0.0 if side > 0 else style.pole_spacing / 2
            for s0 in np.arange(offset + 5.0, total - 5.0, style.pole_spacing):
                p, t = at(s0)
                n = np.array([t[1], -t[0]]) * side
                c = p + n * (r.half_width + 0.6)
                if clear_of_roads(c[None], 0.3):
                    z = float(ground.height(c[0], c[1]))
                    b.cylinder(c[0], c[1], 0.1, z - 0.2, z + rng.uniform(6.0, 8.0), KIND_POLE)
            for s0 in np.arange(16.0, total - 16.0, 6.5):
                p, t = at(s0)
                if near_junction(p, 18.0):
                    continue
                n = np.array([t[1], -t[0]]) * side
                c = p + n * (r.half_width - 1.1)
                z = float(ground.height(c[0], c[1]))
                ln, ht = rng.uniform(4.0, 5.0), rng.uniform(1.4, 1.7)
                if rng.random() < 0.1:
                    ln, ht = rng.uniform(5.0, 6.5), rng.uniform(2.1, 2.8)  # vans
                parking.append(
                    (c[0], c[1], ln / 2, 0.9, z, z + ht, float(np.arctan2(t[1], t[0])), KIND_CAR)
                )
    # Signs at junctions.
    for p in nodes:
        if rng.random() < 0.6:
            ang = rng.uniform(0, 2 * np.pi)
            c = p + 9.5 * np.array([np.cos(ang), np.sin(ang)])
            if clear_of_roads(c[None], 0.3):
                z = float(ground.height(c[0], c[1]))
                top = z + rng.uniform(2.4, 3.2)
                b.cylinder(c[0], c[1], 0.05, z - 0.2, top, KIND_POLE)
                b.box(c[0], c[1], 0.35, 0.03, top - 0.1, top + 0.6, ang, KIND_SIGN)
    # Park and garden trees on free land.
    w, h = cfg.size
    n_park = int(style.park_tree_density * w * h / 1000.0)
    cand = rng.uniform([0.0, 0.0], [w, h], (n_park, 2))
    for c in cand:
        pad = _box_samples(c, np.array([1.0, 1.0]), 0.0, 1.0)
        if occ.free(pad):
            occ.mark(_box_samples(c, np.array([0.5, 0.5]), 0.0, 1.0))
            b.tree(rng, ground, c[0], c[1], style.crown_radius)

    scene = b.freeze()
    pk = np.asarray(parking, dtype=np.float64).reshape(-1, 8)
    slots = Boxes(
        pk[:, 0:2].copy(),
        pk[:, 2:4].copy(),
        pk[:, 4:6].copy(),
        pk[:, 6].copy(),
        pk[:, 7].astype(np.int8),
    )
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
