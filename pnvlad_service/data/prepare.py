"""A recorded drive -> one benchmark run: submaps cut along the trajectory, filtered by G.

A *drive* is a sequence of LiDAR scans with their poses (the
:class:`~pnvlad_service.data.drive.Drive` protocol; the sources are in
:mod:`pnvlad_service.data.sources`). This module accumulates the scans of a stretch of
trajectory in the world frame, cuts a submap every ``stride`` metres of travelled distance, runs
the filter G (:mod:`pnvlad_service.preprocess.filter_g`) on each and writes the benchmark's files
(see docs/PREPARE.md and BENCHMARK_FORMAT.md)::

    <out_run_dir>/pointcloud_20m_10overlap/<timestamp>.bin   training layout, every 10 m
    <out_run_dir>/pointcloud_locations_20m_10overlap.csv
    <out_run_dir>/pointcloud_20m/<timestamp>.bin             test layout, every 20 m
    <out_run_dir>/pointcloud_locations_20m.csv
    <out_run_dir>/pointcloud_keyframes/<timestamp>.bin       keyframes (kind "keyframe"): one
    <out_run_dir>/pointcloud_locations_keyframes.csv         scan every 5 m, G with a range crop
    <out_run_dir>/raw_scans/<timestamp>.bin, raw_scans.csv   with raw_scans=True: the raw scan
                                                             at each test submap (data.scans)

Conventions (docs/ARCHITECTURE.md): world frame x = easting, y = northing, z = up, UTM metres;
timestamps are integer microseconds. Translations are snapped to a 2**-26 m (15 nm) grid
(:func:`~pnvlad_service.data.drive.snap_m`) so that adding a UTM origin and subtracting the
submap centre are exact in float64: the same drive placed at northing 0 or 5.7e6 gives
byte-identical submaps.

:func:`prepare_drive` runs the steps in order: check the drive and options, plan each kind's
cuts and the windows they share, claim the output folders, make and write every window's
submap, then write the locations CSVs. The pieces it runs live beside it: where submaps are cut
(:mod:`.cuts`), scans read once and laid together (:mod:`.accumulate`), the folders claimed and
their frame rows journalled (:mod:`.run_folder`), the true poses of synth's drives
(:mod:`.truth`, which also rewrites an older run's: ``refresh_truth``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from pnvlad_service.data.accumulate import ScanCache, accumulate, travelled_distance, used_scans
from pnvlad_service.data.cuts import (
    Cut,
    Kind,
    Layout,
    check_box_m,
    resolve_geometry,
    submap_cuts,
)
from pnvlad_service.data.drive import Drive, check_drive, snap_m
from pnvlad_service.data.frames import SubmapFrame, frames_path, journal_line, write_frames_csv
from pnvlad_service.data.motion import drive_motion, motion_columns
from pnvlad_service.data.run_folder import claim_folders, journal_path, recorded_frames
from pnvlad_service.data.scans import RAW_CSV, RAW_FOLDER, write_raw_scans_csv, write_scan
from pnvlad_service.data.tree import write_locations_csv
from pnvlad_service.data.truth import drive_true_poses, true_columns
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import write_submap
from pnvlad_service.io.utm import normalize_zone
from pnvlad_service.preprocess.filter_g import GConfig, GResult, apply_g, scan_config

log = logging.getLogger(__name__)


@dataclass
class LayoutResult:
    """What :func:`prepare_drive` did for one layout folder."""

    kind: str
    folder: Path
    csv: Path
    submaps: int = 0
    written: int = 0
    resumed: int = 0
    failed: int = 0


@dataclass
class PrepareResult:
    """Summary of a prepare call: one :class:`LayoutResult` per kind, scans read, seconds."""

    out_run_dir: Path
    layouts: list[LayoutResult] = field(default_factory=list)
    scans_read: int = 0
    seconds: float = 0.0

    def submaps_per_second(self) -> float:
        """Submaps written per second of wall time (0 when nothing was written)."""
        n = sum(r.written for r in self.layouts)
        return n / self.seconds if self.seconds > 0 else 0.0


@dataclass(frozen=True)
class _Options:
    """The settings of one prepare call that every window shares (checked)."""

    config: GConfig
    seed: int
    max_points_per_scan: int | None
    max_range_m: float | None
    scan_step: int
    min_scan_spacing_m: float
    keyframe_config: GConfig
    utm_zone: str = ""


@dataclass
class _KindPlan:
    """One kind of submap of a prepare call: its result record, geometry, G and cuts."""

    result: LayoutResult
    window_m: float
    box_m: float | None
    stride_m: float
    cuts: list[Cut]
    config: GConfig


@dataclass
class _Window:
    """One window to accumulate and filter, and the files (one per kind) it is written to.

    ``single``: a keyframe, the centre scan alone and whole (no ``max_points_per_scan``
    subset); ``raw``: the folder the raw scan at the centre is kept in (``raw_scans``)."""

    cut: Cut
    box_m: float | None
    config: GConfig
    single: bool = False
    raw: Path | None = None
    targets: list[tuple[LayoutResult, Path]] = field(default_factory=list)


def _check_options(
    kinds: Sequence[str],
    config: GConfig,
    keyframe_config: GConfig,
    *,
    seed: int,
    max_points_per_scan: int | None,
    max_range_m: float | None,
    scan_step: int,
    min_scan_spacing_m: float,
    utm_zone: str = "",
) -> _Options:
    """The shared settings, checked: ``InputError`` naming the argument that is out of range
    (or the UTM zone that is malformed: :mod:`pnvlad_service.io.utm`)."""
    if scan_step < 1:
        raise InputError(f"must be >= 1, got {scan_step}", "scan_step")
    if not (math.isfinite(min_scan_spacing_m) and min_scan_spacing_m >= 0):
        raise InputError(f"must be >= 0 metres, got {min_scan_spacing_m}", "min_scan_spacing_m")
    if max_points_per_scan is not None and max_points_per_scan < 1:
        raise InputError(f"must be >= 1, got {max_points_per_scan}", "max_points_per_scan")
    if not kinds:
        raise InputError("no kind of submap asked for", "kinds")
    return _Options(
        config,
        seed,
        max_points_per_scan,
        max_range_m,
        scan_step,
        min_scan_spacing_m,
        keyframe_config,
        normalize_zone(utm_zone),
    )


def _plan(
    out: Path,
    layout: str,
    kinds: Sequence[str],
    window_m: float | None,
    box_m: float | None,
    strides_m: dict[str, float],
    travelled: np.ndarray,
    stamps: np.ndarray,
    opts: _Options,
    raw_scans: bool = False,
) -> tuple[list[_KindPlan], list[_Window]]:
    """Each kind's cuts, and the windows to make in drive order.

    Windows are keyed by their centre distance and length, so a window two kinds share (the
    test cuts are every other train cut with the default strides) is made once and written to
    both folders. Keyframes take the layout's keyframe geometry whatever ``window_m`` and
    ``box_m`` say (those are the submaps'), and ``opts.keyframe_config``. With ``raw_scans``
    the test cuts' windows keep their centre scan raw.
    """
    resolved = []
    for kind in dict.fromkeys(kinds):
        own = (None, None) if kind == "keyframe" else (window_m, box_m)
        resolved.append((kind, *resolve_geometry(layout, kind, *own, strides_m.get(kind))))
    if raw_scans and "test" not in kinds:
        raise InputError("raw scans are kept at the test submaps: ask for the test kind", "kinds")
    plans: list[_KindPlan] = []
    windows: dict[tuple[float, float], _Window] = {}
    for kind, folder, csv_name, window, box, stride in resolved:
        config = opts.keyframe_config if kind == "keyframe" else opts.config
        res = LayoutResult(kind=kind, folder=out / folder, csv=out / csv_name)
        cuts = submap_cuts(travelled, window, stride)
        res.submaps = len(cuts)
        plans.append(_KindPlan(res, window, box, stride, cuts, config))
        for cut in cuts:
            w = windows.setdefault(
                (round(cut.distance_m, 6), window), _Window(cut, box, config, window == 0)
            )
            if w.box_m != box:
                raise InputError("kinds sharing a window must share the box", "box_m")
            if raw_scans and kind == "test":
                w.raw = out / RAW_FOLDER
            w.targets.append((res, res.folder / f"{stamps[cut.scan]}.bin"))
    order = sorted(windows.values(), key=lambda w: (w.cut.first, w.cut.distance_m))
    return plans, order


def _manifest(
    drive: Drive, scans: int, layout: str, plan: _KindPlan, opts: _Options
) -> dict[str, Any]:
    """The parameters of one kind's folder, as :mod:`pnvlad_service.data.run_folder` records
    them in ``.prepare-<folder>.json``."""
    return {
        "format": "pnvlad-prepare",
        "version": 1,
        "drive": getattr(drive, "name", "drive"),
        "scans": scans,
        "layout": layout,
        "kind": plan.result.kind,
        "window_m": plan.window_m,
        "box_m": plan.box_m,
        "stride_m": plan.stride_m,
        "seed": opts.seed,
        "max_points_per_scan": opts.max_points_per_scan,
        "max_range_m": opts.max_range_m,
        "scan_step": opts.scan_step,
        "min_scan_spacing_m": opts.min_scan_spacing_m,
        "g_config": plan.config.model_dump(mode="json"),
        **({"utm_zone": opts.utm_zone} if opts.utm_zone else {}),
    }


def laid_window(
    cut: Cut,
    cache: ScanCache,
    poses: np.ndarray,
    use: np.ndarray,
    box_m: float | None,
    *,
    single: bool = False,
) -> np.ndarray:
    """The cloud G is given for ``cut``: float64 [M, 3] metres, UTM axes about the centre
    scan. The window's scans that ``use`` keeps (and the centre scan), each the ``cache``'s
    seeded subset, laid by :func:`~.accumulate.accumulate` and cut to ``box_m``; ``single``: the
    centre scan alone and whole (a keyframe). ``benchmarks/submap_extent.py`` lays windows
    through it to measure them before G."""
    if single:
        scans = {cut.scan: cache.full(cut.scan)}
        indices = [cut.scan]
    else:
        indices = [i for i in range(cut.first, cut.last + 1) if use[i]]
        if cut.first <= cut.scan <= cut.last and cut.scan not in indices:
            indices.append(cut.scan)
        scans = {i: cache.get(i) for i in indices}
    return accumulate(poses, scans, indices, poses[cut.scan, :3, 3], box_m)


def _window_submap(
    window: _Window,
    cache: ScanCache,
    poses: np.ndarray,
    stamps: np.ndarray,
    use: np.ndarray,
    opts: _Options,
) -> GResult | None:
    """G's result for one window (its points: float64 [target_points, 3]), or ``None``
    (logged) when G cannot make a submap from its points."""
    cut = window.cut
    cache.evict_before(cut.first)
    local = laid_window(cut, cache, poses, use, window.box_m, single=window.single)
    try:
        if len(local) == 0:
            raise InputError("no points in the window", f"scan {cut.scan}")
        return apply_g(local, window.config, seed=opts.seed + cut.scan)
    except InputError as exc:
        log.warning(
            "submap at %.1f m (timestamp %d) skipped: %s", cut.distance_m, stamps[cut.scan], exc
        )
        return None


class _Recorded(NamedTuple):
    """What the drive recorded, scan by scan: ``poses`` float64 [T, 4, 4], ``stamps`` int64
    [T], the simulator's ``true`` poses or ``None``, and the ``motion`` float64 [T, 3] its
    poses give (:func:`~.motion.drive_motion`)."""

    poses: np.ndarray
    stamps: np.ndarray
    true: np.ndarray | None
    motion: np.ndarray


def _frame(
    cut: Cut, g: GResult, recorded: _Recorded, use: np.ndarray | None = None, single: bool = False
) -> SubmapFrame:
    """The sidecar row of the submap cut at ``cut`` (see :mod:`..frames`). The local frame has
    UTM axes at the snapped centre-scan position (what :func:`accumulate` used); its true pose
    is :func:`..truth.frame_truth`'s; a ``single`` scan (a keyframe) carries its motion."""
    poses, stamps, true, motion = recorded
    origin = snap_m(poses[cut.scan, :3, 3])
    true_pos = true_yaw = None
    if true is not None:
        true_pos, true_yaw = true_columns(poses, true, cut, origin, use)
    stamp = int(stamps[cut.scan])
    moving = motion_columns(motion[cut.scan]) if single else None
    return SubmapFrame(stamp, origin, g.centre, g.scale, "enu", true_pos, true_yaw, moving)


def _known_frames(plans: list[_KindPlan]) -> dict[tuple[str, int], SubmapFrame]:
    """(kind, timestamp) -> the frame rows an earlier run recorded (for ``resume``)."""
    known: dict[tuple[str, int], SubmapFrame] = {}
    for plan in plans:
        res = plan.result
        known.update(((res.kind, f.timestamp), f) for f in recorded_frames(res.csv, res.folder))
    return known


@dataclass
class _Made:
    """What :func:`_make_submaps` made: the (kind, centre scan) that failed, the frame
    row of every submap that exists (kind, centre scan) -> row, and the centre scans kept raw."""

    failed: set[tuple[str, int]] = field(default_factory=set)
    frames: dict[tuple[str, int], SubmapFrame] = field(default_factory=dict)
    raw: list[int] = field(default_factory=list)


def _make_submaps(
    windows: list[_Window],
    cache: ScanCache,
    drive: _Recorded,
    use: np.ndarray,
    opts: _Options,
    *,
    known: dict[tuple[str, int], SubmapFrame],
    progress: bool,
    desc: str,
) -> _Made:
    """Make and write every window's submap and its frame row.

    ``drive``: what the drive recorded. A target in ``known`` (resume) already
    on disk with the size of a whole submap is kept, with its recorded frame row.
    """
    from pnvlad_service.progress import tqdm

    made = _Made()
    journals = {}
    for res in {id(r): r for w in windows for r, _ in w.targets}.values():
        # Rewritten with what is known, so that a crash now loses none of it either.
        journals[res.kind] = journal_path(res.csv, res.folder).open("w", encoding="utf-8")
        journals[res.kind].writelines(
            journal_line(f) for (k, _), f in known.items() if k == res.kind
        )
    bar = tqdm(windows, desc=desc, unit="submap", disable=None if progress else True)
    try:
        for window in bar:
            _make_window(window, cache, drive, use, opts, known, made, journals)
    finally:
        bar.close()
        for j in journals.values():
            j.close()
    return made


def _make_window(
    window: _Window,
    cache: ScanCache,
    drive: _Recorded,
    use: np.ndarray,
    opts: _Options,
    known: dict[tuple[str, int], SubmapFrame],
    made: _Made,
    journals: dict[str, Any],
) -> None:
    """One window of :func:`_make_submaps`: its submap written to each target folder that
    lacks it, each frame row recorded in ``made`` and in the kind's journal."""
    poses, stamps = drive.poses, drive.stamps
    whole = window.config.target_points * 3 * 8  # bytes of a finished .bin (float64 x, y, z)
    scan = window.cut.scan
    if window.raw is not None:
        raw = window.raw / f"{stamps[scan]}.bin"
        if not raw.is_file():  # written atomically: one that exists is whole
            write_scan(raw, cache.full(scan))
        made.raw.append(scan)
    todo = []
    for res, path in window.targets:
        old = known.get((res.kind, int(stamps[scan])))
        if old is not None and path.is_file() and path.stat().st_size == whole:
            res.resumed += 1
            made.frames[(res.kind, scan)] = old
        else:
            todo.append((res, path))
    if not todo:
        return
    g = _window_submap(window, cache, poses, stamps, use, opts)
    for res, path in todo:
        if g is None:
            res.failed += 1
            made.failed.add((res.kind, scan))
            continue
        write_submap(path, g.points)
        row = _frame(window.cut, g, drive, use, single=window.single)
        journals[res.kind].write(journal_line(row))
        journals[res.kind].flush()
        made.frames[(res.kind, scan)] = row
        res.written += 1


def _write_locations(
    plans: list[_KindPlan],
    drive: _Recorded,
    made: _Made,
    raw_csv: Path | None = None,
) -> None:
    """Each kind's frame sidecar and locations CSV (its submaps that were made, in cut
    order), written last, the CSV after its sidecar; then ``raw_csv`` listing the raw scans
    kept (:mod:`.scans`)."""
    poses, stamps, true, _ = drive
    if raw_csv is not None:
        rows = [(int(stamps[i]), poses[i], None if true is None else true[i]) for i in made.raw]
        write_raw_scans_csv(raw_csv, rows)
        log.info("%s: %d raw scans -> %s", raw_csv.parent / RAW_FOLDER, len(rows), raw_csv.name)
    for plan in plans:
        res = plan.result
        cuts = [c for c in plan.cuts if (res.kind, c.scan) not in made.failed]
        rows = [
            (int(stamps[c.scan]), float(poses[c.scan, 1, 3]), float(poses[c.scan, 0, 3]))
            for c in cuts
        ]
        write_frames_csv(frames_path(res.csv), [made.frames[(res.kind, c.scan)] for c in cuts])
        write_locations_csv(res.csv, rows)
        journal_path(res.csv, res.folder).unlink(missing_ok=True)
        log.info(
            "%s: %d submaps (%d written, %d already there, %d failed) -> %s",
            res.folder,
            len(rows),
            res.written,
            res.resumed,
            res.failed,
            res.csv.name,
        )


def keep_fixes(drive: Drive, out: Path) -> None:
    """A drive laid onto position fixes (``fixes`` and ``laid_at_fixes``, as
    :class:`~.sources.fix_odometry.FixOdometryDrive` has) keeps them beside the run
    (``fixes.csv``: what marks the run as fix-only for ``pnvlad map align``); any other drive
    removes one an earlier prepare left there."""
    from pnvlad_service.data.sources.fixes import FIXES_CSV, write_run_fixes

    fixes = getattr(drive, "fixes", None)
    if fixes is None:
        (out / FIXES_CSV).unlink(missing_ok=True)
        return
    write_run_fixes(out, fixes, drive.laid_at_fixes)  # type: ignore[attr-defined]


def prepare_drive(
    drive: Drive,
    out_run_dir: str | Path,
    *,
    layout: Layout = "oxford",
    kinds: Sequence[Kind] = ("train", "test"),
    window_m: float | None = None,
    box_m: float | None = None,
    strides_m: dict[str, float] | None = None,
    g_config: GConfig | None = None,
    keyframe_config: GConfig | None = None,
    seed: int = 0,
    max_points_per_scan: int | None = 10_000,
    max_range_m: float | None = None,
    scan_step: int = 1,
    min_scan_spacing_m: float = 0.05,
    raw_scans: bool = False,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    utm_zone: str = "",
) -> PrepareResult:
    """Cut one drive into the submaps of several kinds (default: train and test) in one pass.

    - ``layout``: ``oxford`` or ``inhouse`` (folder and CSV names, default geometry);
      ``kinds``: ``train``, ``test`` and/or ``keyframe`` (single scans, one every
      ``KEYFRAME_STRIDE_M`` unless ``strides_m`` says otherwise, each whole through
      ``keyframe_config``: default :func:`~.filter_g.scan_config`, G with a range crop).
    - ``window_m``: travelled distance accumulated per submap (default: the layout's, 20 m
      oxford, 25 m inhouse), centred on the submap position.
    - ``box_m``: side of a square crop (UTM-aligned) around the submap position (default: none
      for oxford, 25 m for inhouse; 0 disables it; negative, NaN or infinite: ``InputError``
      naming ``box_m``). Recorded in each folder's prepare record, so that ``pnvlad index
      build`` writes it into the bundle's ``map.accumulation`` and accumulated queries
      (:class:`~.accumulate.WindowAccumulator`) are cut to the same box.
    - ``strides_m``: kind -> distance travelled between submaps (default: the layout's, 10 m
      train; 20 m test oxford, 25 m test inhouse).
    - ``g_config`` / ``seed``: the filter G's settings; submap ``k`` uses ``seed`` + the index of
      its centre scan, so results do not depend on the order submaps are made in.
    - ``max_points_per_scan`` (random subset per scan, seeded by scan index), ``max_range_m``
      (drop points farther from the sensor), ``scan_step`` (every k-th scan) and
      ``min_scan_spacing_m`` (skip scans less than this far along the trajectory from the last
      one used: a car waiting at a light adds one scan) keep the accumulation fast.
    - ``raw_scans``: also keep the raw scan at each test submap, sensor frame, with its poses
      (:mod:`.scans`: the single-scan queries of ``pnvlad eval --queries scans``).
    - ``resume``: keep submaps already on disk with the right size (same parameters required);
      ``overwrite``: remove what the folders hold first. ``utm_zone``: the zone of the poses
      (``30U``, :mod:`pnvlad_service.io.utm`), recorded for ``pnvlad index build``.

    Every scan is read once (windows slide forward over a cache); a window shared by two kinds
    runs G once and is written to both folders. A submap is named by the timestamp of its
    centre scan and tagged, in the CSV, with that scan's position (northing, easting); the CSVs
    are written last, atomically.

    Returns a :class:`PrepareResult`. Raises :class:`InputError` on a bad drive or arguments,
    ``FileExistsError`` on output folders that hold submaps, without ``resume``/``overwrite``.
    """
    started = time.perf_counter()
    out = Path(out_run_dir)
    stamps, poses = check_drive(drive)
    check_box_m(box_m, allow_zero=True)  # checked even where only keyframes (no box) are cut
    opts = _check_options(
        kinds,
        g_config if g_config is not None else GConfig(),
        keyframe_config if keyframe_config is not None else scan_config(),
        seed=seed,
        max_points_per_scan=max_points_per_scan,
        max_range_m=max_range_m,
        scan_step=scan_step,
        min_scan_spacing_m=min_scan_spacing_m,
        utm_zone=utm_zone,
    )
    travelled = travelled_distance(poses)
    use = used_scans(travelled, min_scan_spacing_m, scan_step)
    plans, windows = _plan(
        out, layout, kinds, window_m, box_m, strides_m or {}, travelled, stamps, opts, raw_scans
    )
    # Only now, with every argument checked, touch the output folders.
    manifests = [_manifest(drive, len(stamps), layout, plan, opts) for plan in plans]
    targets = [(p.result.folder, p.result.csv) for p in plans]
    if raw_scans:
        targets.append((out / RAW_FOLDER, out / RAW_CSV))
        manifests.append({**manifests[0], "kind": "raw_scans", "g_config": None})
    known = _known_frames(plans) if resume else {}  # before claiming: that drops old sidecars
    claim_folders(targets, manifests, out, resume=resume, overwrite=overwrite)
    cache = ScanCache(
        drive, seed=seed, max_points_per_scan=max_points_per_scan, max_range_m=max_range_m
    )
    recorded = _Recorded(
        poses, stamps, drive_true_poses(drive, len(stamps)), drive_motion(stamps, poses)
    )
    made = _make_submaps(
        windows,
        cache,
        recorded,
        use,
        opts,
        known=known,
        progress=progress,
        desc=f"prepare {out.name}",
    )
    _write_locations(plans, recorded, made, out / RAW_CSV if raw_scans else None)
    keep_fixes(drive, out)
    return PrepareResult(out, [p.result for p in plans], cache.reads, time.perf_counter() - started)
