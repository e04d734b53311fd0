"""Following a drive: a verified pose for every scan, place recognition only to start and to
recover, and an honest "lost".

A robot asking once per scan trusts each answer alone; a localisation stack *tracks*: once it
has a fix it predicts the next pose with its odometry and confirms it by registering the new
scan to the map around the prediction (koide3/hdl_localization's predict / correct split), and
it asks place recognition again only when tracking fails. :class:`DriveLocalizer` is that loop,
on the caller's side: the server stays stateless (a query with a prior pose is just a
registration near it, :mod:`.prior`), so a fleet scales by replicas.

The localiser consumes scans in time order (:class:`DriveScan`: points, timestamp and, when the
caller has it, an odometry pose) and knows nothing of where they come from (a bag, a KITTI
folder, a live sensor), nor of where the answers come from: ``ask(points, prior)`` is a server
or a bundle in this process (:mod:`.service`), ``prior`` ``None`` for a search; it reads the
typed :class:`~.service.Reply`. States:

- ``searching``: each scan is searched for (retrieval and verification). A verified answer is a
  *candidate* fix; it is accepted only when ``confirm`` candidates agree with the odometry
  between them (the motion from one to the next within ``agree_m`` and ``agree_deg`` of what
  the odometry says), so one ambiguous street cannot throw the robot elsewhere. Then: tracking.
- ``tracking``: the pose is predicted (the last pose moved by the odometry's motion, or at
  constant velocity without odometry) and the scan registered near the prediction. A
  registration that fits (the server's ``verified``) and moves the prediction by at most
  ``gate_m`` / ``gate_deg`` is the scan's verified pose; otherwise the prediction is kept,
  unverified, and the failure counted.
- ``lost``: ``failures`` in a row; the scan that makes it says so, and the next one searches.

After a loss the localiser still knows where it last was: the last verified pose, carried on by
the odometry since. A search answer farther from that reckoning than ``reach_m`` plus
``reach_share`` of the distance driven since cannot be where the robot is unless it was carried
away (a street off the map can look like a mapped one 1 km away): it is not a candidate but is
*checked* by tracking it as a hypothesis (registrations near it moved by the odometry, poses not
reported), and it becomes the fix only once its registrations have held over ``far_confirm_m``
metres driven without ``failures`` in a row, which a look-alike street does not and a kidnapped
robot's true place does. A reset (a gap, jumping odometry, a scan out of order) forgets the
last pose: there the reckoning cannot be trusted.

A scan out of time order, a gap of more than ``max_gap_s`` between scans, or odometry that
moves faster than a vehicle can (``max_speed_mps``, ``max_turn_dps``) sends the localiser back
to searching with a line saying why; nothing raises. Every :class:`Step` says its state, its
pose, how sure it is (the fit's fitness and standard deviation, or the search's confidence) and
why it changed state. Measured choices (``confirm``, ``failures``, the gates, the radius):
docs/TRACKING.md.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.fusion import PlanarFilter, heading, with_block
from pnvlad_service.localization.drive.rules import TrackerConfig
from pnvlad_service.localization.drive.service import Ask, Reply
from pnvlad_service.localization.verify.prior import Prior

__all__ = [
    "LOST", "SEARCHING", "STATES", "TRACKING", "DriveLocalizer", "DriveScan", "Step",
    "TrackerConfig", "follow", "scaled_motion", "wrap_deg", "yaw_of",
]  # fmt: skip

SEARCHING = "searching"
TRACKING = "tracking"
LOST = "lost"
STATES = (SEARCHING, TRACKING, LOST)


@dataclass(frozen=True)
class DriveScan:
    """One scan of a drive: its ``index`` in the drive, ``timestamp`` (µs), ``points`` float
    [N, 3] (sensor frame, metres) and ``odometry`` float [4, 4] (sensor -> the odometry's own
    frame, any origin; ``None`` when the caller has none)."""

    index: int
    timestamp: int
    points: np.ndarray
    odometry: np.ndarray | None = None


@dataclass
class Step:
    """What the localiser made of one scan.

    ``state`` after the scan (``searching``, ``tracking`` or ``lost``); ``verified``: this
    scan's ``pose`` (sensor -> UTM, float64 [4, 4]) was confirmed by the map (a registration
    near the prediction, or an accepted fix); ``how``: ``fix`` (search answers that agree),
    ``registered`` (tracking), ``predicted`` (the prediction kept after a failed registration,
    unverified) or ``None`` (no pose); ``fitness`` / ``sigma_m``: the registration's fit and
    largest horizontal standard deviation; ``confidence``: a search answer's; ``anchor``: the
    map entry (``submap_id``) the pose was registered to; ``event``: ``fix`` (the first),
    ``relocalised`` (a later fix), ``lost`` or ``reset`` (bad input: searching again);
    ``reason``: why the state changed or why the scan has no verified pose; ``reply``: the
    service's :class:`~.service.Reply` (its timings), ``None`` when none was asked;
    ``covariance``: float64 [6, 6] of a registered pose (x, y, z, then rotations about them;
    the x, y and heading block the weighed one when the registration was weighed against the
    odometry), else ``None``; ``seconds``: wall time.
    """

    scan: int
    timestamp: int
    state: str
    verified: bool = False
    pose: np.ndarray | None = None
    how: str | None = None
    fitness: float | None = None
    sigma_m: float | None = None
    confidence: float | None = None
    anchor: str | None = None
    event: str | None = None
    reason: str | None = None
    reply: Reply | None = field(default=None, repr=False)
    covariance: np.ndarray | None = field(default=None, repr=False)
    seconds: float = 0.0


@dataclass(frozen=True)
class _Candidate:
    """A verified search answer waiting for others that agree with it."""

    timestamp: int
    pose: np.ndarray
    odometry: np.ndarray | None
    anchor: str | None


@dataclass
class _Reckoning:
    """Where the robot was last verified (``pose``, at ``odometry``) and how far it has driven
    since by its odometry (``driven_m``): where it can be after a loss."""

    pose: np.ndarray
    odometry: np.ndarray
    driven_m: float = 0.0

    def now(self, odometry: np.ndarray) -> np.ndarray:
        return self.pose @ np.linalg.inv(self.odometry) @ odometry


@dataclass
class _Hypothesis:
    """A verified search answer far from the reckoning, tracked until it holds or fails: its
    ``pose`` now, ``off_m`` from the reckoning when found, ``driven_m`` since, ``registered``
    verified registrations, ``failures`` in a row, ``run`` of the map it registers to."""

    pose: np.ndarray
    off_m: float
    run: str | None
    driven_m: float = 0.0
    registered: int = 0
    failures: int = 0


def yaw_of(pose: np.ndarray) -> float:
    """Heading of a pose's x axis, degrees counter-clockwise from east."""
    return math.degrees(heading(pose))


def wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def scaled_motion(delta: np.ndarray, factor: float) -> np.ndarray:
    """A planar motion float [4, 4] scaled by ``factor`` (its translation and its yaw): the
    constant-velocity prediction over another time step."""
    yaw = math.atan2(delta[1, 0], delta[0, 0]) * factor
    out = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = delta[:3, 3] * factor
    return out


class DriveLocalizer:
    """Follows a drive scan by scan (see the module doc): :meth:`step` each scan in time order.

    ``ask``: the service (:data:`Ask`); ``config``: :class:`TrackerConfig`; ``initial_pose``
    (sensor -> UTM [4, 4]): start tracking there, as hdl_localization's initial pose (a wrong
    one fails ``failures`` times and the localiser searches)."""

    def __init__(
        self,
        ask: Ask,
        config: TrackerConfig | None = None,
        initial_pose: np.ndarray | None = None,
    ) -> None:
        self.ask = ask
        self.config = config or TrackerConfig()
        self.state = SEARCHING
        self._pose: np.ndarray | None = None  # the last pose, verified or predicted ...
        self._stamp_of_pose: int | None = None  # ... of the scan at this time
        self._before: tuple[int, np.ndarray] | None = None  # the one before, for velocity
        self._stamp: int | None = None
        self._odometry: np.ndarray | None = None
        self._failures = 0
        self._run: str | None = None  # the map's drive the last pose was registered to
        self._candidates: deque[_Candidate] = deque()
        self._reckoning: _Reckoning | None = None  # the last verified pose, kept over a loss
        self._hypothesis: _Hypothesis | None = None  # a far answer being checked
        self.fixes = 0  # fixes accepted (the first and each relocalisation)
        fuse = self.config.fuse is not False
        self._filter = PlanarFilter(self.config.odometry_noise()) if fuse else None
        if initial_pose is not None:
            self.state = TRACKING
            self._pose = np.asarray(initial_pose, dtype=np.float64)
            self._stamp_of_pose = None  # set by the first scan's time (below)

    # -- the loop ------------------------------------------------------------------------------

    def step(self, scan: DriveScan) -> Step:
        """The :class:`Step` of one scan (never raises on bad input: it says why)."""
        t0 = time.perf_counter()
        step = self._step(scan)
        step.seconds = time.perf_counter() - t0
        return step

    def _step(self, scan: DriveScan) -> Step:
        cfg = self.config
        odo = None if scan.odometry is None else np.asarray(scan.odometry, dtype=np.float64)
        reset: str | None = None
        dt = None
        if self._stamp is not None:
            dt = (scan.timestamp - self._stamp) / 1e6
            if dt <= 0:
                # Not used: the previous scan stays the reference for the next one.
                why = (
                    f"scan {scan.index} is {-dt:.3f} s older than the one before: out of time "
                    "order, skipped; searching again"
                )
                self._reset(forget=True)
                return Step(scan.index, scan.timestamp, SEARCHING, event="reset", reason=why)
            if dt > cfg.max_gap_s:
                reset = f"a gap of {dt:.1f} s since the scan before (more than {cfg.max_gap_s:g} s)"
        motion = None
        if reset is None and odo is not None and self._odometry is not None and dt is not None:
            motion = np.linalg.inv(self._odometry) @ odo
            moved = float(np.linalg.norm(motion[:2, 3]))
            turned = abs(yaw_of(motion))
            if moved > cfg.max_speed_mps * dt + 1.0 or turned > cfg.max_turn_dps * dt + 5.0:
                reset = (
                    f"odometry jumped {moved:.1f} m and {turned:.0f} deg in {dt:.2f} s (more "
                    f"than {cfg.max_speed_mps:g} m/s or {cfg.max_turn_dps:g} deg/s)"
                )
                motion = None
        self._stamp = scan.timestamp
        self._odometry = odo
        if reset is not None:
            self._reset(forget=True)
        self._drive(motion)
        if self.state == TRACKING:
            step = self._track(scan, motion)
        elif self._hypothesis is not None and motion is not None:
            step = self._check(scan, motion)
        else:
            self._hypothesis = None
            step = self._search(scan)
        if reset is not None:
            step.event = step.event or "reset"
            step.reason = f"{reset}: searching again" + (f"; {step.reason}" if step.reason else "")
        return step

    def _reset(self, forget: bool = False) -> None:
        """Back to searching; ``forget``: the last verified pose too (the odometry since cannot
        be trusted to say where the robot is)."""
        self.state = SEARCHING
        self._pose = None
        self._stamp_of_pose = None
        self._before = None
        self._failures = 0
        self._run = None
        self._candidates.clear()
        self._hypothesis = None
        if self._filter is not None:
            self._filter.clear()
        if forget:
            self._reckoning = None

    def _drive(self, motion: np.ndarray | None) -> None:
        """The odometry's motion since the scan before, added to the distances driven."""
        if self._odometry is None:
            self._reckoning = self._hypothesis = None  # nothing to reckon by
            return
        driven = 0.0 if motion is None else float(np.linalg.norm(motion[:2, 3]))
        for held in (self._reckoning, self._hypothesis):
            if held is not None:
                held.driven_m += driven

    def _set_pose(self, stamp: int, pose: np.ndarray) -> None:
        if self._pose is not None and self._stamp_of_pose is not None:
            self._before = (self._stamp_of_pose, self._pose)
        self._pose = pose
        self._stamp_of_pose = stamp

    def _verified(self, stamp: int, pose: np.ndarray) -> None:
        """A verified pose: the pose, and where the robot is known to have been."""
        self._set_pose(stamp, pose)
        if self._odometry is not None:
            self._reckoning = _Reckoning(pose, self._odometry.copy())

    # -- tracking ------------------------------------------------------------------------------

    def _predict(self, stamp: int, motion: np.ndarray | None) -> np.ndarray:
        assert self._pose is not None
        if motion is not None:
            return self._pose @ motion
        if self._before is not None and self._stamp_of_pose is not None:
            t_before, before = self._before
            span = (self._stamp_of_pose - t_before) / 1e6
            if span > 0:
                delta = np.linalg.inv(before) @ self._pose
                return self._pose @ scaled_motion(delta, (stamp - self._stamp_of_pose) / 1e6 / span)
        return self._pose.copy()

    def _register(
        self, scan: DriveScan, predicted: np.ndarray, run: str | None, state: str
    ) -> tuple[Step, np.ndarray | None, str | None]:
        """The scan registered near ``predicted``: its :class:`Step` (``state``), the verified
        pose when the registration fits within the gates, else ``None`` and why."""
        cfg = self.config
        prior = Prior.of_matrix(predicted, cfg.radius_m, run=run)
        reply: Reply | None
        try:
            reply = self.ask(scan.points, prior)
        except InputError as exc:
            reply, why = None, f"refused: {getattr(exc, 'detail', None) or exc}"
        else:
            why = None
        step = Step(scan.index, scan.timestamp, state, reply=reply)
        if reply is not None:
            step.fitness, step.sigma_m = reply.fitness, reply.sigma_m
        pose = None if reply is None else reply.verified_pose
        if reply is not None and pose is None:
            why = reply.reason or "not verified"
        elif pose is not None:
            why = self._beyond_gates(pose, predicted)
            if why is not None:
                pose = None
        return step, pose, why

    def _beyond_gates(self, pose: np.ndarray, predicted: np.ndarray) -> str | None:
        """Why ``pose`` moved ``predicted`` by more than ``gate_m`` or ``gate_deg``; ``None``
        when within both."""
        cfg = self.config
        off = float(np.linalg.norm(pose[:2, 3] - predicted[:2, 3]))
        turn = abs(wrap_deg(yaw_of(pose) - yaw_of(predicted)))
        if off > cfg.gate_m or turn > cfg.gate_deg:
            return (
                f"the registration moved the prediction {off:.1f} m and {turn:.1f} deg "
                f"(more than {cfg.gate_m:g} m or {cfg.gate_deg:g} deg)"
            )
        return None

    def _track(self, scan: DriveScan, motion: np.ndarray | None) -> Step:
        cfg = self.config
        fil = self._filter
        if fil is not None:
            if motion is None or self._pose is None:
                fil.clear()  # a constant-velocity guess: the registration alone
            else:
                fil.predict(self._pose, motion)
        predicted = self._predict(scan.timestamp, motion)
        step, pose, why = self._register(scan, predicted, self._run, TRACKING)
        reply = step.reply
        if pose is not None and reply is not None:
            step.covariance = reply.covariance
        if fil is not None and reply is not None:
            pose, why = self._weigh(step, predicted, pose, why)
        if pose is not None:
            self._failures = 0
            self._verified(scan.timestamp, pose)
            step.verified, step.pose, step.how = True, pose, "registered"
            step.anchor = _anchor(reply)
            self._run = _group(step.anchor) or self._run
            return step
        self._set_pose(scan.timestamp, predicted)
        step.pose, step.how = predicted, "predicted"
        if reply is not None and reply.uncertain:
            # The scan fits the map around the prediction, but not precisely enough along some
            # direction for a verified pose: the odometry carries the pose on, unverified; not
            # a failure (a long street of facades is not being lost).
            step.reason = f"uncertain, the prediction kept: {why}"
            return step
        self._failures += 1
        if self._failures >= cfg.failures:
            step.state, step.event = LOST, "lost"
            step.reason = (
                f"tracking failed {self._failures} times in a row ({why}): searching again"
            )
            self._reset()
        else:
            step.reason = f"tracking failure {self._failures} of {cfg.failures}: {why}"
        return step

    def _weigh(
        self, step: Step, predicted: np.ndarray, pose: np.ndarray | None, why: str | None
    ) -> tuple[np.ndarray | None, str | None]:
        """The registration weighed against the prediction (:mod:`.fusion`): a verified one
        becomes the weighed pose; one the service did not verify (too loose along a direction,
        fitting under its threshold, or moved farther than its own limit) but that fits at
        ``fuse_min_fitness`` within the tracker's gates is verified when the odometry expects
        it (the Mahalanobis gate) and the weighed pose is precise enough. A verified one
        without a covariance is taken alone and the filter starts again from it. Returns the
        pose (``None``: not verified) and why."""
        cfg, fil, reply = self.config, self._filter, step.reply
        assert fil is not None and reply is not None
        reg, cov = reply.fit_pose, reply.fit_covariance
        if reg is None or cov is None:
            if pose is not None:
                fil.start(None)
            return pose, why
        if pose is None:
            weak = reply.fitness is None or reply.fitness < cfg.fuse_min_fitness
            if weak or not fil.ready:
                return None, why
            if self._beyond_gates(reg, predicted) is not None:
                return None, why
            fused = fil.weigh(predicted, reg, cov)
            if not fused.fused or fused.sigma_m > cfg.max_sigma_m:
                return None, why
        else:
            fused = fil.weigh(predicted, pose, cov)
        fil.commit(fused)
        step.sigma_m = fused.sigma_m
        step.covariance = with_block(cov, fused.P)
        return fused.pose, None

    # -- searching -----------------------------------------------------------------------------

    def _search(self, scan: DriveScan) -> Step:
        cfg = self.config
        self.state = SEARCHING
        while self._candidates and (
            (scan.timestamp - self._candidates[0].timestamp) / 1e6 > cfg.confirm_within_s
        ):
            self._candidates.popleft()
        step = Step(scan.index, scan.timestamp, SEARCHING)
        try:
            reply = self.ask(scan.points, None)
        except InputError as exc:
            step.reason = f"refused: {getattr(exc, 'detail', None) or exc}"
            return step
        step.reply = reply
        step.confidence = reply.confidence
        pose = reply.verified_pose
        if pose is None:
            step.reason = reply.reason or (
                "not verified"
                if reply.verified is False
                else "the service does not verify (a bundle without geometry?)"
            )
            return step
        far = self._beyond_reach(pose)
        if far is not None:
            off, reach = far
            self._hypothesis = _Hypothesis(pose, off, _group(_anchor(reply)))
            step.reason = (
                f"a verified answer {off:.0f} m from where the odometry puts the robot since its "
                f"last verified pose (more than {reach:.0f} m): checked by tracking it over "
                f"{cfg.far_confirm_m:g} m"
            )
            return step
        odo = None if self._odometry is None else self._odometry.copy()
        cand = _Candidate(scan.timestamp, pose, odo, _anchor(reply))
        agree = [c for c in self._candidates if self._agree(c, cand)]
        if len(agree) + 1 < cfg.confirm:
            self._candidates.append(cand)
            need = cfg.confirm - 1 - len(agree)
            step.reason = (
                f"a verified answer; waiting for {need} more that agree"
                f"{'s' if need == 1 else ''} with the odometry"
            )
            return step
        reason = (
            "fix: the first verified answer"
            if cfg.confirm == 1
            else f"fix: {len(agree) + 1} verified answers agree with the odometry between them"
        )
        return self._fix(step, pose, cand.anchor, reason)

    def _fix(self, step: Step, pose: np.ndarray, anchor: str | None, reason: str) -> Step:
        """``step`` becomes a fix at ``pose``: tracking from there."""
        self.state = TRACKING
        self._failures = 0
        self._candidates.clear()
        self._hypothesis = None
        self._before = None
        self._verified(step.timestamp, pose)
        if self._filter is not None:
            self._filter.start(None)
        step.state, step.verified, step.pose, step.how = TRACKING, True, pose, "fix"
        step.anchor = anchor
        self._run = _group(anchor)
        step.event = "fix" if self.fixes == 0 else "relocalised"
        self.fixes += 1
        step.reason = reason
        return step

    def _beyond_reach(self, pose: np.ndarray) -> tuple[float, float] | None:
        """(distance, reach) when ``pose`` is farther from where the odometry carries the last
        verified pose than the robot can have drifted; ``None`` when within it or unknown."""
        cfg = self.config
        if self._reckoning is None or self._odometry is None:
            return None
        now = self._reckoning.now(self._odometry)
        off = float(np.linalg.norm(pose[:2, 3] - now[:2, 3]))
        reach = cfg.reach_m + cfg.reach_share * self._reckoning.driven_m
        return (off, reach) if off > reach else None

    def _check(self, scan: DriveScan, motion: np.ndarray) -> Step:
        """A far answer tracked as a hypothesis: a fix once it has held over ``far_confirm_m``,
        dropped after ``failures`` failures in a row (the next scan searches)."""
        cfg = self.config
        hyp = self._hypothesis
        assert hyp is not None
        predicted = hyp.pose @ motion
        step, pose, why = self._register(scan, predicted, hyp.run, SEARCHING)
        reply = step.reply
        if pose is not None:
            hyp.pose, hyp.failures = pose, 0
            hyp.registered += 1
            hyp.run = _group(_anchor(reply)) or hyp.run
            if hyp.driven_m >= cfg.far_confirm_m:
                return self._fix(step, pose, _anchor(reply), (
                    f"fix: an answer {hyp.off_m:.0f} m from where the odometry put the robot "
                    f"held {_registrations(hyp.registered)} over {hyp.driven_m:.0f} m"
                ))  # fmt: skip
            step.reason = (
                f"checking an answer {hyp.off_m:.0f} m from the odometry's reckoning: "
                f"{_registrations(hyp.registered)} over {hyp.driven_m:.0f} of "
                f"{cfg.far_confirm_m:g} m"
            )
            return step
        hyp.pose = predicted
        if reply is not None and reply.uncertain:
            step.reason = f"checking an answer far from the odometry's reckoning: uncertain ({why})"
            return step
        hyp.failures += 1
        if hyp.failures >= cfg.failures:
            self._hypothesis = None
            step.reason = (
                f"the answer {hyp.off_m:.0f} m from the odometry's reckoning did not hold: "
                f"{hyp.failures} failures in a row ({why}); searching again"
            )
        else:
            step.reason = (
                f"checking an answer far from the odometry's reckoning: failure {hyp.failures} "
                f"of {cfg.failures} ({why})"
            )
        return step

    def _agree(self, a: _Candidate, b: _Candidate) -> bool:
        """Whether fix ``b`` is where fix ``a`` moved by the odometry between them puts it."""
        cfg = self.config
        if a.odometry is None or b.odometry is None:
            # No odometry: only how far apart they may be.
            dt = (b.timestamp - a.timestamp) / 1e6
            gap = float(np.linalg.norm(b.pose[:2, 3] - a.pose[:2, 3]))
            return gap <= cfg.max_speed_mps * dt + cfg.agree_m
        motion = np.linalg.inv(a.odometry) @ b.odometry
        expected = a.pose @ motion
        off = float(np.linalg.norm(expected[:2, 3] - b.pose[:2, 3]))
        turn = abs(wrap_deg(yaw_of(expected) - yaw_of(b.pose)))
        driven = float(np.linalg.norm(motion[:2, 3]))
        return off <= cfg.agree_m + cfg.agree_share * driven and turn <= cfg.agree_deg


def _registrations(n: int) -> str:
    return f"{n} registration{'' if n == 1 else 's'}"


def _group(submap_id: str | None) -> str | None:
    """The map's drive (``dataset/run``) of a ``submap_id`` (``dataset/run/timestamp``)."""
    if not submap_id or submap_id.count("/") < 2:
        return None
    return submap_id.rsplit("/", 1)[0]


def _anchor(reply: Reply | None) -> str | None:
    return None if reply is None or reply.top is None else reply.top.submap_id


def follow(scans: Any, ask: Ask, config: TrackerConfig | None = None, **kw: Any) -> list[Step]:
    """Every :class:`DriveScan` of ``scans`` through one :class:`DriveLocalizer`."""
    loc = DriveLocalizer(ask, config, **kw)
    return [loc.step(s) for s in scans]
