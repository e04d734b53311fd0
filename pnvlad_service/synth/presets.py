"""The shipped ``pnvlad synth`` presets: :class:`SynthPreset` (areas, runs, sensors, run
conditions, street detail) and :data:`PRESETS` by name (:func:`get_preset`).

The spinning-sensor presets (``tiny``, ``demo``, ``benchmark``, ``benchmark_v1``) and the
push-broom ones (``pushbroom_tiny``, ``pushbroom_demo``, ``oxford``, ``oxford_tiny``): a SICK
LMS-151 mounted as the Oxford RobotCar's ``lms_front``
(:class:`~pnvlad_service.synth.sensors.PushbroomConfig`), its lines laid with the run's recorded
poses and cut as the PointNetVLAD paper cut Oxford: the points recorded along 20 m of
trajectory, every 10 m (training) and 20 m (testing), in a city with street variety
(:class:`~pnvlad_service.synth.world.StreetVariety`). ``oxford`` is the paper's Oxford: an old
town over the RobotCar's coordinates, partial runs, the published layout.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, SerializerFunctionWrapHandler, model_serializer

from pnvlad_service.errors import InputError
from pnvlad_service.synth.runs import RunConditions
from pnvlad_service.synth.sensors import LidarConfig, PushbroomConfig, pushbroom, sensor
from pnvlad_service.synth.world import CityDetail, StreetVariety


class AreaSpec(BaseModel):
    """One area (a dataset folder of the tree): a district of the city and its route."""

    name: str
    district: str
    size: tuple[float, float] = Field((900.0, 700.0), description="extent x, y, metres")
    origin: tuple[float, float] = Field(
        (620000.0, 5735000.0), description="UTM easting, northing of the area's local origin"
    )
    route_m: float = Field(1500.0, gt=50, description="route length driven by every run, m")
    test_regions: Literal["route", "published"] = Field(
        "route",
        description="route: squares chosen on the area's route (test_share, region_half_size); "
        "published: the benchmark's own, for an area named oxford laid over Oxford's UTM "
        "coordinates (its route must pass through some of them)",
    )


class SynthPreset(BaseModel):
    """Everything that defines a generated benchmark apart from the seed."""

    name: str
    areas: list[AreaSpec]
    runs: int = Field(5, ge=2, description="runs per area")
    lidar: LidarConfig = Field(default_factory=LidarConfig)
    conditions: RunConditions = Field(default_factory=RunConditions)
    scan_spacing: float = Field(2.0, gt=0, description="metres driven between two scans")
    max_points_per_scan: int = Field(10_000, ge=100, description="points kept per scan before G")
    test_share: float = Field(
        0.35, gt=0, lt=1, description="share of each route inside the test regions"
    )
    region_half_size: float = Field(150.0, gt=0, description="test squares are ± this, m")
    keyframe_stride: float | None = Field(
        5.0, gt=0, description="metres between keyframes (single-scan map entries); None: none"
    )
    raw_scans: bool = Field(True, description="keep the raw scan at each test submap")
    lidars: list[LidarConfig] = Field(
        default_factory=list,
        description="sensors the runs are recorded with, run k of area a with lidars[(a + k) % "
        "len] (a map of one sensor met by queries of another); empty: ``lidar`` for every run",
    )
    city: CityDetail = Field(
        default_factory=CityDetail, description="street detail beyond the first benchmarks'"
    )
    box_m: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="submaps cut to the square of this side (metres) centred on the submap's "
        "location, UTM-aligned, before G (prepare_drive's box_m); None: every return of the "
        "20 m window, out to the sensor's range",
    )

    pushbroom: PushbroomConfig | None = Field(
        None,
        description="a line scanner every run is recorded with instead (push-broom: a line "
        "every speed / rate_hz metres; ``lidar`` and ``lidars`` unused)",
    )
    partial_runs: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="share of the runs after the first that drive only part of the route "
        "(a stretch of 35-80 % of it, from a random start), as the benchmark's partial runs",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # A preset without a line scanner dumps as before there was one (its synth.json and
        # the jobs' bytes unchanged).
        out = handler(self)
        if self.pushbroom is None:
            out.pop("pushbroom", None)
        if not self.partial_runs:
            out.pop("partial_runs", None)
        return out

    def run_part(self, area_index: int, run: int, seed: int) -> tuple[float, float] | None:
        """The stretch of the route run ``run`` drives, as shares of its length (start, end);
        None: all of it (always the first run, on which the test regions are chosen)."""
        if run == 0 or not self.partial_runs:
            return None
        rng = np.random.default_rng(np.random.SeedSequence([seed, area_index, run, 13]))
        if rng.random() >= self.partial_runs:
            return None
        share = float(rng.uniform(0.35, 0.8))
        start = float(rng.uniform(0.0, 1.0 - share))
        return (round(start, 4), round(start + share, 4))

    def run_lidar(self, area_index: int, run: int) -> LidarConfig | PushbroomConfig:
        """The sensor run ``run`` of area ``area_index`` is recorded with."""
        if self.pushbroom is not None:
            return self.pushbroom
        if not self.lidars:
            return self.lidar
        return self.lidars[(area_index + run) % len(self.lidars)]


def _areas(route_m: float, size: tuple[float, float], names: tuple[str, ...]) -> list[AreaSpec]:
    # Areas side by side 2 km apart in easting, like neighbouring districts of one city.
    return [
        AreaSpec(
            name=n,
            district=n,
            size=size,
            origin=(619000.0 + 2000.0 * i, 5734500.0 + 300.0 * i),
            route_m=route_m,
        )
        for i, n in enumerate(names)
    ]


#: Run conditions of the realistic presets: the vehicle clear of parked and oncoming cars,
#: cars of several shapes, the sensor pitched and rolled with the slope.
REAL_CONDITIONS = RunConditions(ego_clearance=0.3, vehicle_shapes=True, follow_ground=True)
#: Run conditions of the push-broom presets: the realistic ones with the GNSS/INS error
#: decorrelating over 200 m rather than 60 m. A push-broom submap is stitched from 150 lines,
#: so the error's change along 20 m of trajectory shears it: correlated over 60 m, the position
#: error drifts about 0.9 m and stretches the line spacing by up to 10 % within a submap (the
#: comb of its lines at 0.14 m where the lines were 0.128 m apart); over 200 m, 0.5 m.
PUSHBROOM_CONDITIONS = REAL_CONDITIONS.model_copy(update={"noise_correlation_m": 200.0})
#: Street detail of the realistic presets.
REAL_CITY = CityDetail(
    hedges=0.35,
    bollard_spacing=1.5,
    furniture_per_100m=3.0,
    shrubs_per_1000m2=0.6,
    crown_clumps=4,
    grass_verges=0.5,
    lawns=0.6,
    hills=3.0,
    bridges_per_km=0.6,
    facade_bays=0.5,
    balconies=0.3,
)
#: Street detail of the push-broom presets: the realistic city with streets whose 30-40 m
#: pieces differ (building heights, roofs, setbacks, gaps and open lots, trees of many sizes,
#: avenues), what a push-broom submap must be told apart by.
VARIED_CITY = REAL_CITY.model_copy(update={"variety": StreetVariety()})
#: The oxford preset's area: the old town laid over the RobotCar's UTM coordinates (zone 30U),
#: its 0.9 x 1.3 km holding the benchmark's four published test squares.
OXFORD_AREA = AreaSpec(
    name="oxford",
    district="oldtown",
    size=(920.0, 1270.0),
    origin=(619780.0, 5734600.0),
    route_m=5000.0,
    test_regions="published",
)

PRESETS: dict[str, SynthPreset] = {
    # For tests: a small block, three runs, a sparse sensor. A few seconds.
    "tiny": SynthPreset(
        name="tiny",
        areas=_areas(260.0, (360.0, 300.0), ("business",)),
        runs=3,
        lidar=LidarConfig(beams=32, columns=360),
        scan_spacing=4.0,
        max_points_per_scan=3000,
        test_share=0.4,
        region_half_size=60.0,
    ),
    # The README's main job: one district, four runs, a few hundred submaps.
    "demo": SynthPreset(
        name="demo",
        areas=_areas(1000.0, (700.0, 600.0), ("business",)),
        runs=4,
        lidar=sensor("hdl64e", columns=900),
        conditions=REAL_CONDITIONS,
        city=REAL_CITY,
        scan_spacing=2.5,
        max_points_per_scan=8000,
        test_share=0.35,
        region_half_size=120.0,
    ),
    # Our quality figures: three districts, five runs each, each run recorded with one of four
    # real sensors, streets with hedges, furniture and cars of several shapes.
    "benchmark": SynthPreset(
        name="benchmark",
        areas=_areas(3000.0, (1000.0, 800.0), ("business", "residential", "campus")),
        runs=5,
        lidars=[sensor(name) for name in ("hdl64e", "hdl32e", "vlp16", "os128")],
        conditions=REAL_CONDITIONS,
        city=REAL_CITY,
        scan_spacing=2.5,
        max_points_per_scan=8000,
        test_share=0.45,
        region_half_size=150.0,
    ),
    # The first benchmark (one perfect 64-beam sensor, boxes for cars, no street detail):
    # what the figures of docs/results before 2026-12-05 were first measured on.
    "benchmark_v1": SynthPreset(
        name="benchmark_v1",
        areas=_areas(3000.0, (1000.0, 800.0), ("business", "residential", "campus")),
        runs=5,
        lidar=LidarConfig(columns=1200),
        scan_spacing=2.5,
        max_points_per_scan=8000,
        test_share=0.45,
        region_half_size=150.0,
    ),
    # The PointNetVLAD paper's own sensor, for tests: a short street, three runs. Seconds.
    "pushbroom_tiny": SynthPreset(
        name="pushbroom_tiny",
        areas=_areas(200.0, (360.0, 300.0), ("business",)),
        runs=3,
        pushbroom=pushbroom("lms151"),
        conditions=PUSHBROOM_CONDITIONS,
        city=VARIED_CITY,
        max_points_per_scan=1000,
        test_share=0.4,
        region_half_size=60.0,
        keyframe_stride=None,
        raw_scans=False,
    ),
    # The push-broom beside the demo: one district, four runs, a few minutes.
    "pushbroom_demo": SynthPreset(
        name="pushbroom_demo",
        areas=_areas(1000.0, (700.0, 600.0), ("business",)),
        runs=4,
        pushbroom=pushbroom("lms151"),
        conditions=PUSHBROOM_CONDITIONS,
        city=VARIED_CITY,
        max_points_per_scan=1000,
        test_share=0.35,
        region_half_size=120.0,
        keyframe_stride=None,
        raw_scans=False,
    ),
    # The paper's Oxford: an old-town route of 5 km over the RobotCar's own UTM coordinates
    # (through the benchmark's four test squares), eight runs, a third of the later ones partial,
    # recorded with the push-broom and written in the published layout.
    "oxford": SynthPreset(
        name="oxford",
        areas=[OXFORD_AREA],
        runs=8,
        pushbroom=pushbroom("lms151"),
        conditions=PUSHBROOM_CONDITIONS,
        city=VARIED_CITY,
        max_points_per_scan=1000,
        keyframe_stride=None,
        raw_scans=False,
        partial_runs=0.35,
    ),
    # The same for tests: a corner of it, 300 m into the first test square, three runs (the
    # last one partial). Seconds.
    "oxford_tiny": SynthPreset(
        name="oxford_tiny",
        areas=[
            OXFORD_AREA.model_copy(
                update={"size": (360.0, 300.0), "origin": (619664.0, 5735513.0), "route_m": 300.0}
            )
        ],
        runs=3,
        pushbroom=pushbroom("lms151"),
        conditions=PUSHBROOM_CONDITIONS,
        city=VARIED_CITY,
        max_points_per_scan=1000,
        keyframe_stride=None,
        raw_scans=False,
        partial_runs=0.99,
    ),
}


def get_preset(name: str) -> SynthPreset:
    """A shipped preset by name (a copy: callers may change it)."""
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}", "preset")
    return PRESETS[name].model_copy(deep=True)
