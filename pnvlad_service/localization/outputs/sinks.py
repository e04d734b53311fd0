"""Where a drive's steps go besides its CSV: the :class:`Sink` interface every output shows,
and :class:`Outputs`, the list of sinks a run hands each step to.

A sink is started once with the ``map`` frame and the map (:meth:`Sink.start`), handed each
:class:`~.step.DriveStep` in order (:meth:`Sink.step`) and closed (:meth:`Sink.close`: the
files it wrote). :class:`Outputs` keeps a sink's failure to itself: a sink that raises (a
port in use, a disk full, an unwritable folder) is dropped with a one-line error and the
drive goes on, so its CSV is complete; :attr:`Outputs.errors` says what failed.

The ``map`` frame's origin comes from the map when the run knows it (:class:`~.step.MapView`),
else from the first step with a pose or a truth; the steps before it wait (they carry no
position). The latitude and longitude of a pose need the map's UTM zone: unknown (``""``),
they are left out; a zone that cannot be parsed is one error, and the outputs go on without
them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Protocol

from pnvlad_service.errors import InputError
from pnvlad_service.localization.outputs.step import DriveStep, Frames, MapView

log = logging.getLogger(__name__)


class Sink(Protocol):
    """One output of a drive: ``name`` says what it is in an error (``--mcap drive.mcap``)."""

    name: str

    def start(self, frames: Frames, view: MapView | None) -> None:
        """Before the first step: the ``map`` frame and the map (``None``: not known)."""

    def step(self, step: DriveStep) -> None:
        """One scan, in order."""

    def close(self) -> list[Path]:
        """After the last step (or a failure): finish, return the files written."""


#: UTM (zone, easting, northing) -> (latitude, longitude), degrees.
LatLon = Callable[[str, float, float], tuple[float, float]]


def utm_latlon(zone: str, east: float, north: float) -> tuple[float, float]:
    """WGS 84 latitude and longitude (degrees) of a UTM position (``io/utm.py``, pyproj)."""
    from pnvlad_service.io.utm import to_latlon

    lat, lon = to_latlon(zone, east, north)
    return float(lat), float(lon)


def check_zone(zone: str | None) -> str:
    """The zone as ``io/utm.py`` writes it, ``""`` when unknown; InputError naming
    ``utm_zone`` when it cannot be parsed."""
    from pnvlad_service.io.utm import normalize_zone

    return normalize_zone(zone, "utm_zone")


class Outputs:
    """The sinks of one run, handed each step in order; a failing sink is dropped with a
    one-line error (:attr:`errors`), the others go on. ``latlon``: how a pose's latitude and
    longitude are found (default: :func:`utm_latlon`)."""

    def __init__(self, sinks: Iterable[Sink], latlon: LatLon | None = None) -> None:
        self.sinks: list[Sink] = list(sinks)
        self.errors: list[str] = []
        self.written: list[Path] = []
        self._latlon = latlon or utm_latlon
        self._frames: Frames | None = None
        self._view: MapView | None = None
        self._waiting: list[DriveStep] = []
        self._zone = ""
        self._closed = False

    def __bool__(self) -> bool:
        return bool(self.sinks)

    def fail(self, sink: Sink, exc: BaseException) -> None:
        """Drop ``sink`` with a one-line error (and close what it can)."""
        text = f"{sink.name}: {getattr(exc, 'detail', None) or exc}".splitlines()[0]
        log.error("%s (the drive goes on without it)", text)
        self.errors.append(text)
        self.sinks.remove(sink)
        with contextlib.suppress(Exception):
            getattr(sink, "abort", sink.close)()

    def add(self, opener: Callable[[], Sink]) -> None:
        """Open one sink (``opener()``); a failure to open is one error, not the end."""
        try:
            self.sinks.append(opener())
        except (OSError, RuntimeError, InputError) as exc:
            text = str(exc).splitlines()[0]  # an InputError's names its file
            log.error("%s (the drive goes on without it)", text)
            self.errors.append(text)

    def start(self, view: MapView | None, utm_zone: str | None = None) -> None:
        """The map (``None``: unknown; the frame then waits for a position) and its zone
        (default: the map's)."""
        zone = view.utm_zone if utm_zone is None and view is not None else utm_zone or ""
        try:
            zone = check_zone(zone)
        except InputError as exc:
            self.errors.append(str(exc))
            log.error("%s: latitude and longitude left out", exc)
            zone = ""
        if view is not None:
            view = dataclasses.replace(view, utm_zone=zone)
            self._begin(view.frames(), view)
        else:
            self._zone = zone

    def _begin(self, frames: Frames, view: MapView | None) -> None:
        self._frames, self._view = frames, view
        for sink in list(self.sinks):
            try:
                sink.start(frames, view)
            except Exception as exc:
                self.fail(sink, exc)

    def step(self, step: DriveStep) -> None:
        """Hand ``step`` to every sink (after the frame is known)."""
        if not self.sinks:
            return
        if self._frames is None:
            where = step.pose if step.pose is not None else step.truth
            if where is None:
                self._waiting.append(step)
                return
            self._begin(Frames.around([where[0, 3]], [where[1, 3]], self._zone), None)
            waiting, self._waiting = self._waiting, []
            for s in waiting:
                self._hand(s)
        self._hand(step)

    def _hand(self, step: DriveStep) -> None:
        assert self._frames is not None
        if self._frames.utm_zone and step.pose is not None and step.latlon is None:
            try:
                ll = self._latlon(self._frames.utm_zone, float(step.pose[0, 3]),
                                  float(step.pose[1, 3]))  # fmt: skip
                step = dataclasses.replace(step, latlon=ll)
            except (InputError, ImportError) as exc:  # ImportError: the geo extra missing
                self.errors.append(str(exc))
                log.error("%s: latitude and longitude left out", exc)
                self._frames = dataclasses.replace(self._frames, utm_zone="")
        for sink in list(self.sinks):
            try:
                sink.step(step)
            except Exception as exc:
                self.fail(sink, exc)

    def close(self) -> list[Path]:
        """Close every sink (starting them first when no step had a position); the files
        written."""
        if self._closed:
            return self.written
        self._closed = True
        if self._frames is None and self.sinks:
            self._begin(Frames((0.0, 0.0), self._zone), None)
            for s in self._waiting:
                self._hand(s)
        for sink in list(self.sinks):
            try:
                self.written.extend(sink.close())
            except Exception as exc:
                self.errors.append(f"{sink.name}: {exc}".splitlines()[0])
        return self.written

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_outputs(
    *,
    foxglove: tuple[str, int] | None = None,
    mcap: str | Path | None = None,
    ros2_bag: str | Path | None = None,
    trajectories: str | Path | None = None,
) -> Outputs:
    """The :class:`Outputs` the options ask for: the live view (``foxglove``: host, port) and
    its MCAP (``mcap``) in one :class:`~.foxglove_view.FoxgloveView`, a ROS 2 bag
    (:class:`~.ros2bag.Ros2Bag`), the TUM / KITTI files under ``trajectories``
    (:class:`~.trajectory.Trajectories`). One that cannot be opened is an error in
    :attr:`Outputs.errors` and is left out."""
    outputs = Outputs(())
    if foxglove is not None or mcap is not None:
        from pnvlad_service.localization.outputs.foxglove_view import FoxgloveView

        outputs.add(lambda: FoxgloveView(foxglove, mcap))
    if ros2_bag is not None:
        from pnvlad_service.localization.outputs.ros2bag import Ros2Bag

        outputs.add(lambda: Ros2Bag(ros2_bag))
    if trajectories is not None:
        from pnvlad_service.localization.outputs.trajectory import Trajectories

        outputs.add(lambda: Trajectories(trajectories))
    return outputs
