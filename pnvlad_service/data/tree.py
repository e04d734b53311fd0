"""Benchmark trees on disk: the layouts of the PointNetVLAD benchmark, location CSVs, checks.

A tree root holds dataset folders (``oxford/``, ``inhouse_datasets/``, or the synthetic city's
areas ``business/``, ``residential/`` ...), each holding run folders. A run folder holds the
submaps of one or both roles of a layout (see ``LAYOUTS``):

- ``train``: the training layout (Oxford ``pointcloud_20m_10overlap``, a submap every 10 m);
- ``test``: the test layout (Oxford ``pointcloud_20m``, a submap every 20 m);
- ``keyframe``: single scans, one every few metres of the drive (``pointcloud_keyframes``: each
  one scan through G with a fixed range crop, the map kind a single-scan query meets best;
  ours, not the published benchmark's, which other tools ignore),

each as a folder of ``<timestamp>.bin`` files (float64 x, y, z interleaved, 4096 points,
98,304 bytes, no header) and a CSV ``timestamp,northing,easting`` (timestamp: integer
microseconds; northing, easting: UTM metres of the submap's centroid).

Hidden entries (names starting with ``.``, e.g. the temporary folders of an interrupted atomic
write) and plain files beside the run folders (``test_regions.json``) are ignored.
"""

from __future__ import annotations

import csv
import logging
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from pnvlad_service.data.frames import SubmapFrame, check_frames, frames_path
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text, read_csv_text
from pnvlad_service.io.submap import SUBMAP_BOUND, SUBMAP_BYTES, SUBMAP_POINTS, read_submap

log = logging.getLogger(__name__)

Kind = Literal["train", "test", "keyframe"]
KINDS: tuple[Kind, ...] = ("train", "test", "keyframe")

#: The keyframe maps' folder and CSV, the same in every layout.
KEYFRAME_FOLDER = "pointcloud_keyframes"
KEYFRAME_CSV = "pointcloud_locations_keyframes.csv"

CSV_COLUMNS = ("timestamp", "northing", "easting")


@dataclass(frozen=True)
class Layout:
    """Folder and CSV names of one benchmark layout, for its roles (train, test; keyframe maps
    are named alike in every layout)."""

    name: str
    train_folder: str
    train_csv: str
    test_folder: str
    test_csv: str

    def folder(self, kind: Kind) -> str:
        """Name of the submap folder for ``kind`` ("train", "test" or "keyframe")."""
        return {"train": self.train_folder, "test": self.test_folder}.get(kind, KEYFRAME_FOLDER)

    def csv(self, kind: Kind) -> str:
        """Name of the locations CSV for ``kind`` ("train", "test" or "keyframe")."""
        return {"train": self.train_csv, "test": self.test_csv}.get(kind, KEYFRAME_CSV)

    def names(self) -> tuple[str, ...]:
        own = (self.train_folder, self.train_csv, self.test_folder, self.test_csv)
        return (*own, KEYFRAME_FOLDER, KEYFRAME_CSV)


#: The benchmark's two layouts. Oxford: training submaps every 10 m, test submaps every 20 m.
#: In-house: 25 m boxes, training every 10 m, test every 25 m.
LAYOUTS: dict[str, Layout] = {
    "oxford": Layout(
        name="oxford",
        train_folder="pointcloud_20m_10overlap",
        train_csv="pointcloud_locations_20m_10overlap.csv",
        test_folder="pointcloud_20m",
        test_csv="pointcloud_locations_20m.csv",
    ),
    "inhouse": Layout(
        name="inhouse",
        train_folder="pointcloud_25m_10",
        train_csv="pointcloud_centroids_10.csv",
        test_folder="pointcloud_25m_25",
        test_csv="pointcloud_centroids_25.csv",
    ),
}


@dataclass(frozen=True)
class Locations:
    """The rows of one locations CSV, in file order.

    ``timestamp``: int64 [N] microseconds; ``northing``, ``easting``: float64 [N] UTM metres.
    """

    timestamp: np.ndarray
    northing: np.ndarray
    easting: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamp)

    def rows(self) -> list[tuple[int, float, float]]:
        """The rows as plain ``(timestamp, northing, easting)`` tuples."""
        return [
            (int(t), float(n), float(e))
            for t, n, e in zip(self.timestamp, self.northing, self.easting, strict=True)
        ]


@dataclass(frozen=True)
class Submap:
    """One submap of a benchmark tree.

    ``path`` is relative to the tree root, with ``/`` separators, as the published pickles
    write it: ``oxford/<run>/pointcloud_20m/<timestamp>.bin``. ``timestamp`` is integer
    microseconds; ``northing``/``easting`` are float64 UTM metres of the submap's centroid;
    ``kind`` is the layout role, ``"train"`` or ``"test"``; ``row`` its row in the CSV;
    ``utm_zone`` the UTM zone of the coordinates (``""`` when unknown).
    """

    dataset: str
    run: str
    timestamp: int
    northing: float
    easting: float
    path: str
    kind: Kind
    row: int
    utm_zone: str = ""

    @property
    def submap_id(self) -> str:
        """``dataset/run/timestamp``: unique within a benchmark tree."""
        return f"{self.dataset}/{self.run}/{self.timestamp}"


def read_locations_csv(path: str | Path) -> Locations:
    """Read a benchmark CSV with the columns ``timestamp,northing,easting`` (any order, extra
    columns ignored), keeping the file's row order.

    Raises ``InputError`` naming the file (and the line) for a missing file, a missing column,
    a non-integer timestamp, a non-numeric or non-finite coordinate.
    """
    path = Path(path)
    reader = csv.reader(read_csv_text(path, "locations CSV", "utf-8-sig").splitlines())
    header = next(reader, None)
    if header is None:
        raise InputError("empty file: expected the header 'timestamp,northing,easting'", path)
    names = [h.strip().lower() for h in header]
    missing = [c for c in CSV_COLUMNS if c not in names]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)} in header {','.join(header)!r}; "
            "expected 'timestamp,northing,easting'",
            source=path,
        )
    it, inn, ie = (names.index(c) for c in CSV_COLUMNS)
    need = max(it, inn, ie) + 1
    ts: list[int] = []
    north: list[float] = []
    east: list[float] = []
    for lineno, rec in enumerate(reader, start=2):
        if not rec or all(not f.strip() for f in rec):
            continue
        if len(rec) < need:
            raise InputError(f"line {lineno}: {len(rec)} fields, expected {len(names)}", path)
        t_txt, n_txt, e_txt = rec[it].strip(), rec[inn].strip(), rec[ie].strip()
        try:
            t = int(t_txt)
        except ValueError:
            raise InputError(
                f"line {lineno}: timestamp {t_txt!r} is not an integer (microseconds)", path
            ) from None
        vals = []
        for name, txt in (("northing", n_txt), ("easting", e_txt)):
            try:
                v = float(txt)
            except ValueError:
                raise InputError(f"line {lineno}: {name} {txt!r} is not a number", path) from None
            if not math.isfinite(v):
                raise InputError(f"line {lineno}: {name} is {txt!r}, not a finite number", path)
            vals.append(v)
        ts.append(t)
        north.append(vals[0])
        east.append(vals[1])
    return Locations(
        timestamp=np.asarray(ts, dtype=np.int64),
        northing=np.asarray(north, dtype=np.float64),
        easting=np.asarray(east, dtype=np.float64),
    )


def write_locations_csv(
    path: str | Path, rows: Locations | Iterable[tuple[int, float, float]]
) -> None:
    """Write a benchmark CSV ``timestamp,northing,easting`` atomically.

    ``rows``: a ``Locations`` or ``(timestamp µs, northing m, easting m)`` tuples. Floats are
    written with ``repr`` (the shortest text that reads back to the same float64), so a round
    trip through ``read_locations_csv`` is exact. Non-finite coordinates raise ``InputError``.
    """
    items = rows.rows() if isinstance(rows, Locations) else rows
    lines = [",".join(CSV_COLUMNS)]
    for k, (t, n, e) in enumerate(items):
        n, e = float(n), float(e)
        if not (math.isfinite(n) and math.isfinite(e)):
            raise InputError(f"row {k}: non-finite coordinate ({n}, {e})", source=path)
        lines.append(f"{int(t)},{n!r},{e!r}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def _visible_dirs(path: Path) -> list[str]:
    return sorted(
        e.name for e in os.scandir(path) if e.is_dir() and not e.name.startswith((".", "__"))
    )


def detect_layout(run_dir: str | Path) -> Layout | None:
    """The layout whose folders or CSVs a run folder holds, or ``None``."""
    run_dir = Path(run_dir)
    best: tuple[int, Layout] | None = None
    for layout in LAYOUTS.values():
        hits = sum((run_dir / n).exists() for n in layout.names())
        if hits and (best is None or hits > best[0]):
            best = (hits, layout)
    return None if best is None else best[1]


class BenchmarkTree:
    """A benchmark tree on disk: ``root/<dataset>/<run>/<layout folders and CSVs>``.

    Datasets and runs are listed in sorted order (as the published scripts list them); submaps
    in CSV row order. Reading is lazy and cached per CSV.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("benchmark tree root is not a directory", source=self.root)
        if detect_layout(self.root) is not None or any(
            detect_layout(self.root / d) is not None for d in _visible_dirs(self.root)
        ):
            raise InputError(
                "this looks like a dataset or run folder; pass the tree root that holds the "
                "dataset folders (e.g. benchmark_datasets/, which holds oxford/)",
                source=self.root,
            )
        self._locations: dict[tuple[str, str, Kind], Locations] = {}

    @property
    def datasets(self) -> list[str]:
        """Dataset folder names, sorted."""
        return _visible_dirs(self.root)

    def runs(self, dataset: str) -> list[str]:
        """Run folder names of ``dataset``, sorted (the published scripts' order)."""
        d = self.root / dataset
        if not d.is_dir():
            raise InputError(
                f"no dataset {dataset!r} (have: {', '.join(self.datasets) or 'none'})",
                source=self.root,
            )
        return _visible_dirs(d)

    def layout(self, dataset: str, run: str) -> Layout:
        """The layout of a run; ``InputError`` where the run folder holds none."""
        layout = detect_layout(self.root / dataset / run)
        if layout is None:
            raise InputError(
                "no submap folder or CSV of a known layout "
                f"({', '.join(sorted({n for lay in LAYOUTS.values() for n in lay.names()}))})",
                source=self.root / dataset / run,
            )
        return layout

    def csv_path(self, dataset: str, run: str, kind: Kind) -> Path:
        return self.root / dataset / run / self.layout(dataset, run).csv(kind)

    def locations(self, dataset: str, run: str, kind: Kind) -> Locations:
        """The CSV rows of one run and role (cached)."""
        key = (dataset, run, kind)
        if key not in self._locations:
            self._locations[key] = read_locations_csv(self.csv_path(dataset, run, kind))
        return self._locations[key]

    def has(self, dataset: str, run: str, kind: Kind) -> bool:
        """Whether the run holds a CSV for ``kind``."""
        layout = detect_layout(self.root / dataset / run)
        return layout is not None and (self.root / dataset / run / layout.csv(kind)).is_file()

    def submaps(self, dataset: str, run: str, kind: Kind) -> list[Submap]:
        """The submaps of one run and role, in CSV row order."""
        layout = self.layout(dataset, run)
        loc = self.locations(dataset, run, kind)
        prefix = f"{dataset}/{run}/{layout.folder(kind)}/"
        return [
            Submap(dataset, run, t, n, e, f"{prefix}{t}.bin", kind, k)
            for k, (t, n, e) in enumerate(loc.rows())
        ]

    def frames_by_path(self) -> dict[str, SubmapFrame]:
        """Every submap with a frame sidecar row: its absolute ``.bin`` path -> the row."""
        out: dict[str, SubmapFrame] = {}
        for dataset in self.datasets:
            for run in self.runs(dataset):
                for kind in KINDS:
                    if not self.has(dataset, run, kind):
                        continue
                    rows = self.frames(dataset, run, kind)
                    if rows is None:
                        continue
                    subs = self.submaps(dataset, run, kind)
                    out.update(
                        (str((self.root / s.path).resolve()), f)
                        for s, f in zip(subs, rows, strict=True)
                    )
        return out

    def frames(self, dataset: str, run: str, kind: Kind) -> list[SubmapFrame] | None:
        """The rows of the run's frame sidecar for ``kind`` (:mod:`.frames`), one per submap in
        CSV order, or ``None`` when the run has no sidecar (e.g. the published Oxford files).
        ``InputError`` when the sidecar is bad or does not list the CSV's submaps."""
        side = frames_path(self.csv_path(dataset, run, kind))
        if not side.is_file():
            return None
        return check_frames(side, [int(t) for t in self.locations(dataset, run, kind).timestamp])


# --------------------------------------------------------------------------------------------
# check_tree


@dataclass
class TreeProblem:
    """One thing wrong in a tree: the file or folder and what is wrong with it."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


@dataclass
class DatasetSummary:
    """Counts and UTM extent of one dataset (extent: min/max northing, easting in metres)."""

    name: str
    runs: int = 0
    layouts: set[str] = field(default_factory=set)
    submaps: dict[str, int] = field(default_factory=lambda: dict.fromkeys(KINDS, 0))
    northing: tuple[float, float] = (math.inf, -math.inf)
    easting: tuple[float, float] = (math.inf, -math.inf)

    def extend(self, loc: Locations) -> None:
        if len(loc):
            self.northing = (
                min(self.northing[0], float(loc.northing.min())),
                max(self.northing[1], float(loc.northing.max())),
            )
            self.easting = (
                min(self.easting[0], float(loc.easting.min())),
                max(self.easting[1], float(loc.easting.max())),
            )


@dataclass
class CheckReport:
    """What ``check_tree`` found: a summary per dataset and the list of problems."""

    root: str
    datasets: list[DatasetSummary]
    problems: list[TreeProblem]

    @property
    def ok(self) -> bool:
        return not self.problems


def _check_bin(path: Path, deep: bool) -> str | None:
    """What is wrong with one submap file (its size; with ``deep`` its values), or ``None``."""
    size = path.stat().st_size
    if size != SUBMAP_BYTES:
        what = "truncated" if size < SUBMAP_BYTES else "oversized"
        return f"{what}: {size} bytes, expected {SUBMAP_BYTES} ({SUBMAP_POINTS} points × 3 float64)"
    if deep:
        pts = read_submap(path)
        if not np.isfinite(pts).all():
            return "holds NaN or infinite coordinates"
        if np.abs(pts).max() > SUBMAP_BOUND:
            return f"coordinates outside [-1, 1] (max |value| {np.abs(pts).max():.3g})"
    return None


class _TreeChecker:
    """The problems of one tree, found level by level: a run, one role of it, its files."""

    def __init__(self, tree: BenchmarkTree, deep: bool) -> None:
        self.tree = tree
        self.deep = deep
        self.problems: list[TreeProblem] = []

    def add(self, path: Path, message: str) -> None:
        """Record a problem with ``path`` (named relative to the tree root)."""
        self.problems.append(TreeProblem(path.relative_to(self.tree.root).as_posix(), message))

    def run(self, dataset: str, run: str, summary: DatasetSummary) -> None:
        """Check one run folder: a known layout, then each role it holds."""
        summary.runs += 1
        run_dir = self.tree.root / dataset / run
        layout = detect_layout(run_dir)
        if layout is None:
            self.add(run_dir, "empty run: no submap folder or CSV")
            return
        summary.layouts.add(layout.name)
        for kind in KINDS:
            self.role(run_dir, layout, kind, summary)

    def role(self, run_dir: Path, layout: Layout, kind: Kind, summary: DatasetSummary) -> None:
        """Check one role of a run: its CSV reads, has rows and unique timestamps, has its
        folder; then the folder's files."""
        folder, csv_path = run_dir / layout.folder(kind), run_dir / layout.csv(kind)
        if not folder.exists() and not csv_path.exists():
            return
        if not csv_path.is_file():
            self.add(folder, f"submap folder without {layout.csv(kind)}")
            return
        try:
            loc = read_locations_csv(csv_path)
        except InputError as exc:
            self.add(csv_path, exc.detail)
            return
        if len(loc) == 0:
            self.add(csv_path, "no rows")
        summary.submaps[kind] += len(loc)
        summary.extend(loc)
        uniq, counts = np.unique(loc.timestamp, return_counts=True)
        for t in uniq[counts > 1][:10]:
            self.add(csv_path, f"duplicate timestamp {int(t)}")
        side = frames_path(csv_path)
        if side.is_file():
            try:
                check_frames(side, [int(t) for t in loc.timestamp])
            except InputError as exc:
                self.add(side, exc.detail)
        if not folder.is_dir():
            self.add(csv_path, f"CSV without folder {layout.folder(kind)}")
            return
        self.files(folder, csv_path, loc)

    def files(self, folder: Path, csv_path: Path, loc: Locations) -> None:
        """Every CSV row has its ``.bin`` and every ``.bin`` its row (ten of each listed, the
        rest counted); every matched ``.bin`` is a whole submap."""
        files = {e.name for e in os.scandir(folder) if not e.name.startswith(".")}
        wanted = {f"{int(t)}.bin" for t in loc.timestamp}
        missing = [f"{int(t)}.bin" for t in loc.timestamp if f"{int(t)}.bin" not in files]
        for name in missing[:10]:
            self.add(folder / name, "CSV row without a file")
        if len(missing) > 10:
            self.add(folder, f"{len(missing) - 10} more rows without file")
        extra = sorted(files - wanted)
        for name in extra[:10]:
            self.add(folder / name, f"file without a row in {csv_path.name}")
        if len(extra) > 10:
            self.add(folder, f"{len(extra) - 10} more files without row")
        for name in sorted(files & wanted):
            msg = _check_bin(folder / name, self.deep)
            if msg:
                self.add(folder / name, msg)


def check_tree(root: str | Path, *, deep: bool = False, progress: bool = False) -> CheckReport:
    """Validate a benchmark tree and summarise it.

    Checks, per run and role: the CSV reads (header, integers, finite numbers), no duplicate
    timestamps, every CSV row has its ``.bin`` and every ``.bin`` its row, every ``.bin`` is
    exactly 98,304 bytes; ``deep`` also reads each ``.bin`` and checks its values are finite and
    inside [-1, 1]. Empty datasets and runs, runs without a known layout, a folder without its
    CSV and a CSV without its folder are problems too. Never raises for a bad tree (only when
    ``root`` is not a directory): everything found is in ``report.problems``.
    """
    tree = BenchmarkTree(root)
    checker = _TreeChecker(tree, deep)
    datasets = tree.datasets
    if not datasets:
        checker.problems.append(TreeProblem(str(tree.root), "no dataset folders"))
    summaries = {d: DatasetSummary(d) for d in datasets}
    for d in datasets:
        if not tree.runs(d):
            checker.add(tree.root / d, "empty dataset: no run folders")
    jobs: Iterable[tuple[str, str]] = [(d, r) for d in datasets for r in tree.runs(d)]
    if progress:
        from pnvlad_service.progress import tqdm

        jobs = tqdm(jobs, desc="check", unit="run")
    for d, r in jobs:
        checker.run(d, r, summaries[d])
    report = CheckReport(str(tree.root), list(summaries.values()), checker.problems)
    log.info(
        "checked %s: %d dataset(s), %d problem(s)", tree.root, len(summaries), len(checker.problems)
    )
    return report


def format_report(report: CheckReport, max_problems: int = 50) -> str:
    """A plain-text table of a ``CheckReport`` (datasets, runs, submaps, UTM extent)."""
    head = (
        f"{'dataset':<20} {'layout':<14} {'runs':>5} {'train':>8} {'test':>8} {'keyframe':>8}"
        "  UTM extent (m)"
    )
    lines = [head, "-" * len(head)]
    for s in report.datasets:
        ext = (
            f"N {s.northing[0]:.1f}..{s.northing[1]:.1f}  E {s.easting[0]:.1f}..{s.easting[1]:.1f}"
            if math.isfinite(s.northing[0])
            else "-"
        )
        lay = ",".join(sorted(s.layouts)) or "-"
        lines.append(
            f"{s.name:<20} {lay:<14} {s.runs:>5} {s.submaps['train']:>8} {s.submaps['test']:>8}"
            f" {s.submaps['keyframe']:>8}  {ext}"
        )
    if report.problems:
        lines.append("")
        lines.append(f"{len(report.problems)} problem(s):")
        lines.extend(f"  {p}" for p in report.problems[:max_problems])
        if len(report.problems) > max_problems:
            lines.append(f"  ... and {len(report.problems) - max_problems} more")
    else:
        lines.append("")
        lines.append("no problems found")
    return "\n".join(lines)
