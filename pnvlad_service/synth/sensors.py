"""The spinning LiDARs the synthetic city can be seen with: :class:`LidarConfig` and the
catalogue :data:`SENSORS` of real models' beam layouts.

A sensor is its beams (elevation angles: evenly spread, or a model's own table), its azimuth
steps per turn and rotation rate, its range window, and how its returns fail as real ones do:
range noise that grows with range, dropouts that grow with range and with the incidence angle,
returns lost on glass and on dark vehicle paint, rays that reach into foliage before they
return, and the vehicle's motion during a sweep (the scan is not de-skewed). Every realism
field defaults to the perfect sensor of the first benchmarks, so that a tree whose
``synth.json`` predates them casts the same scans again; the catalogue's sensors switch them on.

Beam tables (degrees, from the makers' manuals): the Velodyne HDL-64E has an upper block of 32
lasers from +2.0 to -8.33 degrees (1/3 degree apart) and a lower block of 32 from -8.83 to
-24.8 degrees (about 1/2 degree apart); the HDL-32E 32 lasers evenly from +10.67 to -30.67; the
VLP-16 16 from +15 to -15 (2 degrees apart); a 128-beam sensor (Ouster OS1-128) 128 evenly over
+-22.5 degrees.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from pnvlad_service.errors import InputError


class LidarConfig(BaseModel):
    """The spinning sensor. Defaults: a perfect Velodyne HDL-64E-like sensor (64 beams evenly
    from +2° to -24.8°, about 100 m range, 2 cm range noise, 5 % dropouts, no motion)."""

    name: str = Field("", description="the sensor model, for the record (e.g. HDL-64E)")
    beams: int = Field(64, ge=1, description="laser channels")
    elevation_max_deg: float = Field(2.0, description="top beam elevation, degrees")
    elevation_min_deg: float = Field(-24.8, description="bottom beam elevation, degrees")
    elevations_deg: list[float] | None = Field(
        None,
        description="each beam's elevation, degrees (a model's own table); None: ``beams`` "
        "evenly from elevation_max_deg to elevation_min_deg",
    )
    columns: int = Field(1800, ge=8, description="azimuth steps per turn (0.2°)")
    rotation_hz: float = Field(10.0, gt=0, description="turns a second")
    max_range: float = Field(100.0, gt=0, description="metres")
    min_range: float = Field(2.5, ge=0, description="metres; closer returns are dropped")
    range_noise: float = Field(0.02, ge=0, description="range noise std, metres")
    range_noise_per_100m: float = Field(
        0.0, ge=0, description="range noise std added per 100 m of range, metres"
    )
    dropout: float = Field(0.05, ge=0, lt=1, description="share of returns lost")
    dropout_far: float = Field(
        0.0, ge=0, lt=1, description="share lost added at max_range (grows as range squared)"
    )
    dropout_grazing: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="share lost added at a grazing incidence (grows as (1 - cos)^2 of the "
        "angle between the ray and the surface normal)",
    )
    glass_loss: float = Field(
        0.0, ge=0, le=1, description="share of the returns from facade windows lost on glass"
    )
    dark_loss: float = Field(
        0.0, ge=0, lt=1, description="share of the returns from vehicles lost on dark paint"
    )
    foliage_depth: float = Field(
        0.0,
        ge=0,
        description="mean depth (m) a ray reaches into a tree crown before it returns "
        "(0: at the crown's surface)",
    )
    deskewed: bool = Field(
        True,
        description="False: each column is fired as the vehicle moves through the sweep and "
        "the points are given in the sensor frame at the sweep's middle (not de-skewed)",
    )
    mount_height: float = Field(1.9, description="sensor height above the ground, metres")
    ego_roof_drop: float = Field(
        0.0,
        ge=0,
        description="metres the vehicle's roof lies below the sensor; rays that meet the roof "
        "return nothing (0: the vehicle is not in view)",
    )
    ego_roof: tuple[float, float, float] = Field(
        (0.87, 1.0, 0.91),
        description="the roof's reach ahead of, behind and to each side of the sensor, metres; "
        "its outline is two half ellipses through these four points",
    )

    @model_validator(mode="after")
    def _table(self) -> LidarConfig:
        table = self.elevations_deg
        if table is not None:
            if len(table) != self.beams:
                raise ValueError(f"elevations_deg has {len(table)} beams, beams says {self.beams}")
            if not all(np.isfinite(table)):
                raise ValueError("elevations_deg must be finite")
            # The extremes follow the table (what the realism statistics read).
            object.__setattr__(self, "elevation_max_deg", float(max(table)))
            object.__setattr__(self, "elevation_min_deg", float(min(table)))
        if self.elevation_min_deg > self.elevation_max_deg:
            raise ValueError("elevation_min_deg is above elevation_max_deg")
        return self

    def elevations(self) -> np.ndarray:
        """Every beam's elevation, float64 [beams] degrees, highest first."""
        if self.elevations_deg is not None:
            return np.sort(np.asarray(self.elevations_deg, dtype=np.float64))[::-1].copy()
        return np.linspace(self.elevation_max_deg, self.elevation_min_deg, self.beams)

    @property
    def realistic(self) -> bool:
        """Whether any of the real sensor's failures is switched on."""
        return bool(
            self.range_noise_per_100m
            or self.dropout_far
            or self.dropout_grazing
            or self.glass_loss
            or self.dark_loss
            or self.foliage_depth
            or not self.deskewed
            or self.ego_roof_drop
        )


def _hdl64e() -> list[float]:
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return [round(float(v), 3) for v in np.r_[upper, lower]]


#: How real sensors fail, shared by the catalogue: range noise growing 2 cm a 100 m, a fifth of
#: the returns lost at 100 m and a quarter at a grazing incidence, 70 % of facade windows and 30 %
#: of vehicle paint lost, rays reaching 0.6 m into crowns on average, no de-skewing, and the
#: vehicle's roof 0.4 m below the sensor, its outline (``ego_roof``'s default) fitted to KITTI's
#: HDL-64E: of a turn, its beams at -21.7 to -24.8 degrees return 96, 90, 68, 73, 43, 25 and 5 %
#: of what the beam at -21.2 does (frames 0, 52, 4501 of sequence 00), the outline 100, 85, 77,
#: 66, 41, 22 and 0 %.
REAL_FAILURES = {
    "range_noise_per_100m": 0.02,
    "dropout": 0.03,
    "dropout_far": 0.2,
    "dropout_grazing": 0.25,
    "glass_loss": 0.7,
    "dark_loss": 0.3,
    "foliage_depth": 0.6,
    "deskewed": False,
    "ego_roof_drop": 0.4,
}

#: Real sensors by short name; ``pnvlad synth`` presets mix them across runs.
SENSORS: dict[str, LidarConfig] = {
    "hdl64e": LidarConfig(
        name="HDL-64E", beams=64, elevations_deg=_hdl64e(), columns=2000, **REAL_FAILURES
    ),
    "hdl32e": LidarConfig(
        name="HDL-32E",
        beams=32,
        elevation_max_deg=10.67,
        elevation_min_deg=-30.67,
        columns=2170,  # 0.166 degree steps at 10 Hz
        # the roof fitted to the nuScenes car's: its beams at -30.6 to -20.1 degrees return
        # 18, 29, 40, 48, 52, 61, 69, 85, 95 % of a turn, the outline 16, 28, 40, 48, 57, 64,
        # 71, 78, 95 %
        ego_roof=(0.62, 0.70, 1.10),
        **REAL_FAILURES,
    ),
    "vlp16": LidarConfig(
        name="VLP-16",
        beams=16,
        elevation_max_deg=15.0,
        elevation_min_deg=-15.0,
        columns=1800,
        range_noise=0.03,
        **REAL_FAILURES,
    ),
    "os128": LidarConfig(
        name="OS1-128",
        beams=128,
        elevation_max_deg=22.5,
        elevation_min_deg=-22.5,
        columns=1024,
        range_noise=0.015,
        **REAL_FAILURES,
    ),
}


def sensor(name: str, **update: object) -> LidarConfig:
    """A catalogue sensor by name (a copy, ``update`` applied), else ``KeyError``."""
    return SENSORS[name].model_copy(update=update, deep=True)


#: The Oxford RobotCar's front SICK LMS-151 (the RobotCar SDK's ``extrinsics/lms_front.txt``):
#: x, y, z (metres) and roll, pitch, yaw (radians) in the vehicle frame the SDK gives every
#: sensor in (x forward, y right, z down, about the roof's stereo camera), the rotation
#: ``Rz(yaw) Ry(pitch) Rx(roll)`` taking the scanner's axes into it.
LMS_FRONT = (1.759, 0.227, 1.041, -0.044, -1.457, 0.036)

#: The vehicle's body (a Nissan LEAF, 4.45 m x 1.77 m x 1.55 m), as boxes in the city's vehicle
#: frame (x forward, y left, z up, metres; origin on the road below the SDK's reference):
#: x0, x1, y0, y1, z0, z1. The lower body ends at the front bumper, a few centimetres behind
#: the scanner; the cabin starts 1.1 m behind it.
LEAF_BODY = (
    (-2.75, 1.70, -0.885, 0.885, 0.15, 0.95),
    (-2.30, 0.60, -0.800, 0.800, 0.95, 1.55),
)


def _finite(values: tuple[float, ...], name: str) -> tuple[float, ...]:
    if not all(np.isfinite(values)):
        raise ValueError(f"{name}: must be finite, got {list(values)}")
    return values


class PushbroomConfig(BaseModel):
    """A 2D line scanner swept along the street by the vehicle's motion (push-broom). Defaults:
    the SICK LMS-151 (270 degrees in its scan plane, 0.5 degree steps, 50 lines a second,
    about 50 m) mounted as the Oxford RobotCar's ``lms_front``, with the failures of
    :data:`REAL_FAILURES` (a line takes 15 ms: nothing to de-skew).

    Each line is the fan of rays at angles ``-fov/2 .. +fov/2`` about the scanner's x axis in its
    x-y plane; ``mount`` places the scanner in the vehicle frame the RobotCar SDK uses (x
    forward, y right, z down, about a reference point ``reference_height`` above the road).
    """

    kind: Literal["pushbroom"] = "pushbroom"
    name: str = Field("LMS-151", description="the sensor model, for the record")
    fov_deg: float = Field(270.0, gt=0, le=360, allow_inf_nan=False, description="fan, degrees")
    step_deg: float = Field(0.5, gt=0, allow_inf_nan=False, description="angular step, degrees")
    rate_hz: float = Field(50.0, gt=0, allow_inf_nan=False, description="lines a second")
    max_range: float = Field(50.0, gt=0, allow_inf_nan=False, description="metres")
    min_range: float = Field(0.5, ge=0, allow_inf_nan=False, description="metres")
    range_noise: float = Field(0.012, ge=0, description="range noise std, metres")
    range_noise_per_100m: float = Field(0.02, ge=0, description="std added per 100 m, metres")
    dropout: float = Field(0.03, ge=0, lt=1, description="share of returns lost")
    dropout_far: float = Field(0.2, ge=0, lt=1, description="share lost added at max_range")
    dropout_grazing: float = Field(0.25, ge=0, lt=1, description="share lost at grazing")
    glass_loss: float = Field(0.7, ge=0, le=1, description="share of window returns lost")
    dark_loss: float = Field(0.3, ge=0, lt=1, description="share of vehicle returns lost")
    foliage_depth: float = Field(0.6, ge=0, description="mean depth into tree crowns, metres")
    mount: tuple[float, float, float, float, float, float] = Field(
        LMS_FRONT,
        description="x, y, z (m), roll, pitch, yaw (rad) in the vehicle frame: x forward, "
        "y right, z down (the RobotCar SDK's extrinsics)",
    )
    reference_height: float = Field(
        1.75,
        gt=0,
        allow_inf_nan=False,
        description="height of the vehicle frame's origin above the road, metres (the "
        "RobotCar's roof camera: an estimate, the SDK does not give it)",
    )
    body: tuple[tuple[float, float, float, float, float, float], ...] = Field(
        LEAF_BODY,
        description="the vehicle's body as boxes x0, x1, y0, y1, z0, z1 (m; x forward, y left, "
        "z up above the road); rays that meet it return nothing",
    )
    #: the fields the spinning sensors' failure model reads (real_returns), fixed here
    deskewed: bool = True
    rotation_hz: float = 50.0
    realistic: bool = True

    @field_validator("mount")
    @classmethod
    def _mount(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        return _finite(v, "mount")

    @field_validator("body")
    @classmethod
    def _body(cls, v: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        for box in v:
            _finite(box, "body")
            if box[0] >= box[1] or box[2] >= box[3] or box[4] >= box[5]:
                raise ValueError(f"body: a box needs x0 < x1, y0 < y1, z0 < z1, got {box}")
        return v

    @model_validator(mode="after")
    def _placed(self) -> PushbroomConfig:
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range: {self.min_range} is not below max_range")
        if self.step_deg > self.fov_deg:
            raise ValueError(f"step_deg: {self.step_deg} is wider than fov_deg {self.fov_deg}")
        x, y, z = self.origin()
        if z <= 0:
            raise ValueError(f"mount: the scanner is {z:.2f} m above the road (below it)")
        for box in self.body:
            if box[0] < x < box[1] and box[2] < y < box[3] and box[4] < z < box[5]:
                raise ValueError(
                    f"mount: the scanner at x {x:.2f}, y {y:.2f}, z {z:.2f} m (forward, left, "
                    "up) lies inside the vehicle body"
                )
        return self

    def origin(self) -> np.ndarray:
        """The scanner's position in the city's vehicle frame (x forward, y left, z up above
        the road), float64 [3] metres."""
        x, y, z = self.mount[:3]
        return np.array([x, -y, self.reference_height - z])

    def axes(self) -> np.ndarray:
        """The scanner's axes in the city's vehicle frame, float64 [3, 3] (columns: its x, y,
        z): the SDK's ``Rz Ry Rx`` turned from (forward, right, down) to (forward, left, up)."""
        roll, pitch, yaw = self.mount[3:]
        cr, sr, cp, sp, cy, sy = (
            np.cos(roll),
            np.sin(roll),
            np.cos(pitch),
            np.sin(pitch),
            np.cos(yaw),
            np.sin(yaw),
        )
        rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        return np.diag([1.0, -1.0, -1.0]) @ (rz @ ry @ rx)

    def angles(self) -> np.ndarray:
        """Each ray's angle in the scan plane from the scanner's x axis, float64 [R] radians,
        ascending (toward its y axis)."""
        n = int(np.floor(self.fov_deg / self.step_deg + 1e-9)) + 1
        return np.deg2rad(-self.fov_deg / 2 + self.step_deg * np.arange(n))


#: Line scanners by short name.
PUSHBROOMS: dict[str, PushbroomConfig] = {"lms151": PushbroomConfig()}


def pushbroom(name: str = "lms151", **update: object) -> PushbroomConfig:
    """A catalogue line scanner by name with ``update`` applied, checked: an impossible rate,
    field of view or mounting raises :class:`InputError` naming the field, in one line."""
    if name not in PUSHBROOMS:
        raise InputError(
            f"unknown line scanner {name!r}; choose one of {', '.join(PUSHBROOMS)}", "pushbroom"
        )
    return checked_pushbroom({**PUSHBROOMS[name].model_dump(), **update})


def checked_pushbroom(fields: dict[str, Any]) -> PushbroomConfig:
    """A :class:`PushbroomConfig` from ``fields``, or :class:`InputError` naming the first bad
    field (``pushbroom.rate_hz``, ``pushbroom.mount``, ...) with what is wrong, in one line."""
    try:
        return PushbroomConfig.model_validate(fields)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"][:1])
        msg = str(err["msg"]).removeprefix("Value error, ")
        if ": " in msg and (not where or msg.startswith(f"{where}: ")):
            where, msg = msg.split(": ", 1)  # the checks name their field first
        raise InputError(
            f"{msg} (got {err.get('input')!r})" if err["loc"] else msg,
            f"pushbroom.{where}" if where else "pushbroom",
        ) from None
