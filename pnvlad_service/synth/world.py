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
- grass: thin boxes over the ground that a real sensor's rays reach into;

plus a smooth height-field ground (gentle slopes). This module holds the city's model (the
district styles, the config, the primitives, :class:`World`);
:func:`pnvlad_service.synth.city.generate_world` builds one from a seed: same seed and config,
same arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TypeVar

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
)

# Kinds, stored as int8 next to each primitive (used by runs.py for per-run edits and by
# preview.py for colours).
KIND_BUILDING, KIND_WALL, KIND_FENCE, KIND_KERB, KIND_CAR, KIND_SIGN = 0, 1, 2, 3, 4, 5
KIND_TRUNK, KIND_POLE, KIND_PEDESTRIAN, KIND_CONE, KIND_CROWN, KIND_BARRIER = 6, 7, 8, 9, 10, 11
KIND_HEDGE, KIND_BOLLARD, KIND_FURNITURE = 12, 13, 14
KIND_GRASS, KIND_FACADE, KIND_BRIDGE = 15, 16, 17


class DistrictStyle(BaseModel):
    """How a district looks: street grid, building templates, vegetation, furniture."""

    block_size: tuple[float, float] = Field(description="street spacing range, metres")
    jitter: float = Field(12.0, description="junction position jitter, metres")
    curved_share: float = Field(0.25, description="share of streets drawn as curves")
    removed_share: float = Field(0.15, description="share of inner streets removed (T junctions)")
    diagonal_share: float = Field(0.08, description="share of blocks crossed by a diagonal street")
    road_half_width: tuple[float, float] = Field((4.0, 7.0), description="side, main; metres")
    main_columns: bool = Field(
        False, description="main roads along the first and middle columns too (not rows only)"
    )
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
    # An Oxford-like old town: narrow side streets beside wide main roads, terraces and colleges
    # of 2-5 storeys near the kerb, college and garden walls, many large trees.
    "oldtown": DistrictStyle(
        block_size=(75.0, 120.0),
        jitter=15.0,
        curved_share=0.35,
        road_half_width=(3.0, 7.5),
        main_columns=True,
        n_templates=6,
        width=(8.0, 30.0),
        depth=(10.0, 22.0),
        height=(7.0, 18.0),
        wing_share=0.4,
        setback=(0.5, 4.0),
        gap=(0.0, 4.0),
        street_tree_spacing=12.0,
        street_tree_share=0.55,
        park_tree_density=1.5,
        crown_radius=(2.0, 4.5),
        pole_spacing=30.0,
        fence_share=0.15,
        wall_share=0.25,
        parking_share=0.6,
    ),
}


class StreetVariety(BaseModel):
    """How much the pieces of a street differ (applied by
    :func:`pnvlad_service.synth.variety.vary_city`, which describes each piece)."""

    model_config = ConfigDict(extra="forbid")

    height_scale: tuple[float, float] = Field(
        (0.35, 1.1), description="range of a building's height factor (drawn log-uniformly)"
    )
    roofs: float = Field(
        0.6, ge=0, le=1, description="share of buildings with a pitched roof, top storey or plant"
    )
    setback_jitter_m: float = Field(
        5.0, ge=0, le=20, description="most metres a building moves back from its street"
    )
    narrow_share: float = Field(
        0.3, ge=0, le=1, description="share of buildings cut shorter along the street (gaps)"
    )
    vacant_lots: float = Field(
        0.15, ge=0, le=1, description="share of buildings taken away, the lot left open"
    )
    tree_scale: tuple[float, float] = Field(
        (0.55, 1.9), description="range of a tree's size factor (drawn log-uniformly)"
    )
    avenues: float = Field(
        0.2, ge=0, le=1, description="share of street sides planted as an avenue (7-11 m apart)"
    )

    @field_validator("height_scale", "tree_scale")
    @classmethod
    def _range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0 < v[0] <= v[1] <= 5 and np.isfinite(v).all()):
            raise ValueError(f"must be a range low <= high within (0, 5], not {v}")
        return v


class CityDetail(BaseModel):
    """What real streets have beyond the first benchmarks' city (all off by default, so that
    a tree made before them is built again the same): hedges along the pavements' back edge,
    bollards by the junctions, benches, bins and cabinets, shrubs on free land, tree crowns of
    several clumps."""

    model_config = ConfigDict(extra="forbid")

    hedges: float = Field(0.0, ge=0, le=1, description="share of pavement stretches with a hedge")
    bollard_spacing: float = Field(
        0.0, ge=0, description="metres between bollards near junctions (0: none)"
    )
    furniture_per_100m: float = Field(
        0.0, ge=0, description="benches, bins and cabinets per 100 m of pavement"
    )
    shrubs_per_1000m2: float = Field(0.0, ge=0, description="shrubs per 1000 m² of free land")
    crown_clumps: int = Field(
        1, ge=1, le=6, description="ellipsoids a tree crown is made of (1: one smooth crown)"
    )
    grass_verges: float = Field(
        0.0, ge=0, le=1, description="share of pavement stretches with a grass verge by the kerb"
    )
    lawns: float = Field(
        0.0, ge=0, le=1, description="share of the free land within 22 m of a street under grass"
    )
    hills: float = Field(
        0.0,
        ge=0,
        le=6,
        description="amplitude (m) of hills 160-320 m across on top of the gentle ground "
        "(streets up to about 6 % at 3 m); buildings stand on their lowest corner",
    )
    bridges_per_km: float = Field(
        0.0, ge=0, description="bridges over the streets per km of street (decks on two piers)"
    )
    facade_bays: float = Field(
        0.0, ge=0, le=1, description="share of buildings whose street face has piers and recesses"
    )
    balconies: float = Field(
        0.0, ge=0, le=1, description="share of buildings whose street face has balconies"
    )
    variety: StreetVariety | None = Field(
        None,
        description="how much the pieces of a street differ: building heights, roofs, "
        "setbacks, gaps and open lots, tree sizes, avenues (None: the first city's templates)",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, object]:
        # Without variety it dumps as before there was any (older trees' synth.json unchanged).
        out = handler(self)
        if self.variety is None:
            out.pop("variety", None)
        return out

    @property
    def any(self) -> bool:
        return (
            bool(
                self.hedges
                or self.bollard_spacing
                or self.furniture_per_100m
                or self.shrubs_per_1000m2
                or self.grass_verges
                or self.lawns
                or self.bridges_per_km
                or self.facade_bays
                or self.balconies
            )
            or self.crown_clumps > 1
        )


class WorldConfig(BaseModel):
    """Size, district and georeference of one generated area."""

    district: str = Field("business", description="one of DISTRICTS")
    size: tuple[float, float] = Field((900.0, 700.0), description="extent x, y in metres")
    origin: tuple[float, float] = Field(
        (620000.0, 5735000.0), description="UTM easting, northing of the local origin, metres"
    )
    ground_slope: float = Field(0.015, description="largest mean ground gradient (1.5 %)")
    ground_relief: float = Field(2.5, description="amplitude of ground undulation, metres")
    detail: CityDetail = Field(default_factory=CityDetail)


_P = TypeVar("_P", bound="_Primitives")


class _Primitives:
    """A set of N primitives as parallel arrays, one a field, the primitive on the first axis."""

    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    def take(self: _P, keep: np.ndarray) -> _P:
        """The primitives selected by ``keep`` (a mask or indices), every field alike."""
        return type(self)(*(getattr(self, f.name)[keep] for f in fields(self)))

    @classmethod
    def concat(cls: type[_P], *parts: _P) -> _P:
        """One set of all ``parts``, in order, every field concatenated."""
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))


@dataclass
class Boxes(_Primitives):
    """Oriented boxes. center [N,2], half [N,2] (half length, half width), z [N,2] bottom/top,
    yaw [N] radians (rotation of the box's x axis from east), kind int8 [N]. Metres, local."""

    center: np.ndarray
    half: np.ndarray
    z: np.ndarray
    yaw: np.ndarray
    kind: np.ndarray


@dataclass
class Cylinders(_Primitives):
    """Vertical cylinders. center [N,2], radius [N], z [N,2], kind int8 [N]. Metres, local."""

    center: np.ndarray
    radius: np.ndarray
    z: np.ndarray
    kind: np.ndarray


@dataclass
class Ellipsoids(_Primitives):
    """Axis-aligned ellipsoids. center [N,3], radii [N,3], density [N] in (0, 1] (share of
    rays that return from the crown), kind int8 [N]. Metres, local."""

    center: np.ndarray
    radii: np.ndarray
    density: np.ndarray
    kind: np.ndarray


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
