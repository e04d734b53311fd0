"""The odometry's steps refined by the scans: each scan registered onto the one before it.

A tracked drive predicts each scan's pose by moving the last verified pose by the odometry's
step (:mod:`.tracking`), and registers the scan to the map from that prediction. A recorded
pose stream is often poor at that scale: a GNSS/INS fix's error wanders by decimetres between
two scans a few metres apart (the benchmark's drives: the registration moved the prediction
0.37 m at the median, 0.66 m at p90), and a registration started that far off can settle in
the wrong groove of a street whose facades leave the shift along it nearly free. Two
consecutive scans see almost the same street, so the scan registered onto the one before it,
started from the recorded step, gives the step itself to about a centimetre (the map
alignment's steps between keyframes 5 m apart: 1 cm and 0.01 degree at the median,
docs/results/align.md). :class:`ScanSteps` chains those refined steps into an odometry of its own;
the tracker uses it as it would the recorded poses (only their steps count).

A step the registration does not confirm (a degenerate or empty scan, too low a fitness, a
result farther from the recorded step than ``gate_m`` / ``gate_deg``) is the recorded step
as it is: the chain never moves where the recording did not, beyond the gate. A scan without
a recorded pose breaks the chain (the next one starts it again), as it breaks the recorded
odometry.

:class:`StepsAhead` runs a :class:`ScanSteps` in a process of its own, so that a follow
registers the next scan's step while it localises this one (the step's registrations hold the
interpreter's lock while they run, so a thread could not overlap them).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace

import numpy as np

from pnvlad_service.localization.drive.tracking import yaw_of
from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.localization.verify.verify_process import settle_child

#: The registration of one scan onto the one before it: the map alignment's odometry's 0.5 m
#: voxels, with the verification's two threads. Along a street whose facades leave the shift
#: nearly free (the case the refined steps are for) 1 m voxels leave 4-14 cm along it where
#: 0.5 m leave 3 mm (tests/localization/test_scan_steps.py's street); on KITTI 00's scans 94
#: and 95 both are within 7 mm. The coarse cloud is voxelised from the fine one: a scan is
#: prepared every time one arrives, and the second pass over all its points is saved.
STEP_REGISTRATION = reg.RegistrationConfig(fine_voxel_m=0.5, vgicp_leaf_m=0.5, coarse_of_fine=True)


@dataclass(frozen=True)
class ScanStepConfig:
    """``min_fitness``: a registration scoring less leaves the recorded step; ``gate_m`` /
    ``gate_deg``: ... as does one farther than this from it (a GNSS/INS step's own error is
    decimetres and a few tenths of a degree; a registration metres off slid along a street, and
    two scans skewed by a corner turned at 90 degrees a second register degrees off: with 3
    degrees two of the benchmark's runs lost track at such a corner, with 1 none did);
    ``carry_shift``: the registration starts from the recorded step's turn with the last
    refined step's shift (a vehicle's motion changes little between two scans, a recording's
    position error by decimetres: the benchmark's recorded steps are 0.37 m off at the median),
    and from the recorded step only where that start fails the gates; False: from the recorded
    step alone; ``registration``: its settings (started from a given step: no yaw search).

    ``near_m``, ``turning_deg``: a step whose recorded turn is at most ``turning_deg`` is
    registered with the points within ``near_m`` horizontally of the sensor only, and without
    the coarse stage; a sharper one (a corner) with every point and both stages (``near_m``
    None: every step so). A spinning sensor's far returns are sparse rings that cost half a
    scan's preparation and pin a straight step least, and a step started from the last one's
    shift is within centimetres; at a corner turned at 90 degrees a second the two scans are
    skewed, the start is decimetres off, and only the far points and the coarse stage keep
    the step (docs/results/tracking.md)."""

    min_fitness: float = 0.3
    gate_m: float = 1.5
    gate_deg: float = 1.0
    carry_shift: bool = True
    near_m: float | None = 40.0
    turning_deg: float = 2.0
    registration: reg.RegistrationConfig = field(default_factory=lambda: STEP_REGISTRATION)

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_fitness <= 1.0:
            raise ValueError(f"min_fitness must be in [0, 1], got {self.min_fitness}")
        if not (self.gate_m > 0 and self.gate_deg > 0):
            raise ValueError(f"gate_m and gate_deg must be > 0, got {self.gate_m}, {self.gate_deg}")
        if self.near_m is not None and not self.near_m > 0:
            raise ValueError(f"near_m must be > 0 or None, got {self.near_m}")
        if not self.turning_deg >= 0:
            raise ValueError(f"turning_deg must be >= 0, got {self.turning_deg}")

    @property
    def near_registration(self) -> reg.RegistrationConfig:
        """The registration of a step that turns little: no coarse stage."""
        return replace(self.registration, coarse_iterations=0)


class _Scan:
    """One scan's points and its preparations, each made once when first asked for: with
    every point and the coarse stage (``full``), or the near points alone."""

    def __init__(self, points: np.ndarray, config: ScanStepConfig) -> None:
        self.points, self.config = np.asarray(points), config
        self._made: dict[bool, reg.Prepared] = {}

    def prepared(self, full: bool) -> reg.Prepared:
        made = self._made.get(full)
        if made is None:
            c, points = self.config, self.points
            if full:
                made = reg.prepare(points, c.registration, "both", search=False)
            else:
                if c.near_m is not None and points.ndim == 2 and points.shape[1] == 3:
                    xy = points[:, :2]
                    points = points[np.einsum("ij,ij->i", xy, xy) <= c.near_m**2]
                made = reg.prepare(points, c.near_registration, "both", search=False)
            self._made[full] = made
        return made


class ScanSteps:
    """The recorded poses of a drive, each step refined by registering the scan onto the one
    before it (see the module doc). ``refined`` / ``kept``: how many steps the registration
    refined and how many kept the recorded step."""

    def __init__(self, config: ScanStepConfig | None = None) -> None:
        self.config = config or ScanStepConfig()
        self._last: _Scan | None = None
        self._recorded: np.ndarray | None = None
        self._pose: np.ndarray | None = None
        self._step: np.ndarray | None = None
        self.refined = 0
        self.kept = 0

    def update(self, points: np.ndarray, recorded: np.ndarray | None) -> np.ndarray | None:
        """The scan's pose in the chain's own frame (float64 [4, 4]) from its ``points``
        (sensor frame, metres) and its ``recorded`` pose (sensor -> the recording's frame);
        ``None`` when it has no recorded pose."""
        if recorded is None:
            self._last = self._recorded = self._pose = self._step = None
            return None
        scan = _Scan(points, self.config)
        recorded = np.asarray(recorded, dtype=np.float64)
        if self._pose is None or self._recorded is None:
            self._pose = recorded.copy()
        else:
            step = np.linalg.inv(self._recorded) @ recorded
            self._pose = self._pose @ self._refine(scan, step)
        self._last = scan
        self._recorded = recorded
        return self._pose.copy()

    def _refine(self, scan: _Scan, step: np.ndarray) -> np.ndarray:
        """The step from the last scan to ``scan``: registered from the recorded ``step``'s
        turn with the last refined step's shift (where there is one and ``carry_shift``: along
        a street whose facades leave the shift nearly free the registration stays about where
        it starts, and the recording's shift can be a metre off where the vehicle's changed by
        centimetres), then from ``step`` itself if that fails the gates; ``step`` where none
        passes. A step that turns more than ``turning_deg`` is registered with every point
        and the coarse stage, another with the near points alone (:class:`ScanStepConfig`)."""
        c = self.config
        if self._last is None:
            return self._kept(step)
        full = c.near_m is None or abs(yaw_of(step)) > c.turning_deg
        source, target = scan.prepared(full), self._last.prepared(full)
        if source.reason is not None or target.reason is not None:
            return self._kept(step)
        config = c.registration if full else c.near_registration
        starts = [step]
        if c.carry_shift and self._step is not None:
            carried = step.copy()
            carried[:3, 3] = self._step[:3, 3]
            starts.insert(0, carried)
        for start in starts:
            r = reg.register(source, target, config, init=start)
            off_m, off_deg = reg.apart(r.transform, step)
            passes = r.reason is None and r.fitness >= c.min_fitness
            if passes and off_m <= c.gate_m and off_deg <= c.gate_deg:
                self.refined += 1
                self._step = r.transform
                return r.transform
        return self._kept(step)

    def _kept(self, step: np.ndarray) -> np.ndarray:
        self.kept += 1
        self._step = None
        return step


class StepsAhead:
    """A :class:`ScanSteps` in a worker process: :meth:`submit` hands it a scan and returns the
    future of :meth:`ScanSteps.update`'s pose; scans are stepped in the order submitted, as in
    this process (to the millimetres small_gicp's threads vary a step by). The worker starts in
    about a second (a fresh interpreter: the caller may hold threads a fork would copy
    mid-work; a script that makes one must do it under ``if __name__ == "__main__":``, as the
    CLI does: a worker that does not start is a RuntimeError that says so); :meth:`close`
    ends it (also as a context manager)."""

    def __init__(self, config: ScanStepConfig | None = None) -> None:
        self._pool = ProcessPoolExecutor(
            1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_start_worker,
            initargs=(config,),
        )
        try:
            self._pool.submit(_ready).result()
        except (BrokenProcessPool, RuntimeError) as exc:
            self._pool.shutdown(wait=False, cancel_futures=True)
            raise RuntimeError(
                f"the refined steps' worker process did not start ({exc}); a script that follows "
                "a drive of 100 scans or more must do it under `if __name__ == '__main__':` "
                "(multiprocessing's spawn imports the script again in the worker), or pass "
                "ahead=False"
            ) from exc

    def submit(self, points: np.ndarray, recorded: np.ndarray | None) -> Future[np.ndarray | None]:
        return self._pool.submit(_worker_update, points, recorded)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> StepsAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_WORKER: ScanSteps | None = None


def _start_worker(config: ScanStepConfig | None) -> None:
    """The worker's initialiser: it shares the cores with the process that localises, so its
    OpenMP threads sleep while they wait (small_gicp loads in its first step, after this)."""
    global _WORKER
    settle_child()
    _WORKER = ScanSteps(config)


def _ready() -> bool:
    return _WORKER is not None


def _worker_update(points: np.ndarray, recorded: np.ndarray | None) -> np.ndarray | None:
    assert _WORKER is not None, "the worker was not started"
    return _WORKER.update(points, recorded)
