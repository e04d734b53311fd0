"""Every run of a `pnvlad synth` tree followed as a ROS bag against a map of the others.

For each run of each area (or those named): a keyframe bundle of the area's other runs
(``pnvlad index build --layout keyframe``, cached under OUT/maps), the run written as a ROS 2
bag of every scan (``--every``) with its GNSS/INS poses on ``/odom`` and the simulator's truth
on ``/ground_truth``, as ``benchmarks/make_rosbag.py`` writes them, then ``pnvlad localize
--rosbag BAG --pose-topic /odom --truth-topic /ground_truth --index MAP`` (the command, in this
process) follows it: searching until a fix agrees with the odometry, then tracking. Prints one
row a run (its direction, the distance and time to the first fix, the share of the scans after
it with a verified pose, the share within 1 m and 2 degrees of the truth, median and p99 pose
errors against the truth and against the map's own truth, verified poses more than 5 m off,
relocalisations, losses, scans a second) and the totals; the CSVs and PNGs stay in
OUT/replays. ``--per-scan`` asks with every ``--every``-th scan alone instead (the per-scan replay).

    python benchmarks/replay_benchmark.py --root B --model runs/bev_scan/model --out out/follow
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
from entry import run

from pnvlad_service.extras import require


class EveryNth:
    """Scans 0, n, 2n, ... of a drive: ``poses`` the recorded (GNSS/INS) ones, ``true`` the
    simulator's."""

    def __init__(self, drive, n: int) -> None:
        self.drive, self.name = drive, drive.name
        self.index = np.arange(0, len(drive), n)
        self.timestamps = drive.timestamps[self.index]
        self.poses = drive.poses[self.index]
        self.true = drive.true_poses[self.index]

    def __len__(self) -> int:
        return len(self.index)

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(int(self.index[i]))


class MemoEncoder:
    """The model's encoder, each cloud's descriptor kept by the cloud's bytes: an area's maps
    (each its runs but one) embed every keyframe once, not once a map."""

    def __init__(self, model: Path) -> None:
        from pnvlad_service.models.runtimes import load_encoder

        self.encoder = load_encoder(model)
        self.dim = self.encoder.dim
        self.memo: dict[bytes, np.ndarray] = {}

    def embed(self, points: np.ndarray) -> np.ndarray:
        import hashlib

        x = np.ascontiguousarray(points, dtype=np.float32)
        keys = [hashlib.blake2b(c.tobytes(), digest_size=16).digest() for c in x]
        todo = [k for k, key in enumerate(keys) if key not in self.memo]
        if todo:
            for k, d in zip(todo, self.encoder.embed(x[todo]), strict=True):
                self.memo[keys[k]] = d
        return np.stack([self.memo[key] for key in keys])


_ENCODERS: dict[Path, MemoEncoder] = {}


def map_of(root: Path, model: Path, out: Path, area: str, name: str,
           tag: str = "maps") -> Path:  # fmt: skip
    """The keyframe bundle of the area's runs of ``root`` but ``name`` (built once, under
    ``out/TAG``)."""
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.build import build_bundle

    bundle = out / tag / area / f"{name}.index"
    if not (bundle / "manifest.json").is_file():
        others = [r for r in BenchmarkTree(root).runs(area) if r != name]
        if model not in _ENCODERS:
            _ENCODERS[model] = MemoEncoder(model)
        encoder = _ENCODERS[model]
        build_bundle(bundle, model, root, datasets=[area], runs=others, layout="keyframe",
                     progress=False, encoder=encoder)  # fmt: skip
    return bundle


def model_tag(model: Path) -> str:
    """A folder name for a model: its run's name (``runs/a/model`` -> ``a``) or its own."""
    model = Path(model)
    return model.parent.name if model.name == "model" and model.parent.name else model.name


def drive_name(every: int, off_map: tuple[float, float] | None, kidnap: str | None) -> str:
    """The bag's folder name: the scans taken and the excursion."""
    name = f"every{every}"
    if off_map:
        name += f"-offmap{off_map[0]:g}-back{off_map[1]:g}"
    if kidnap:
        name += f"-kidnap{kidnap.replace(':', '-')}"
    return name


def drive_of(root: Path, area: str, name: str, off_map: tuple[float, float] | None = None,
             kidnap: str | None = None):  # fmt: skip
    """The run cast again from the tree's ``synth.json`` (its recorded GNSS/INS poses and the
    simulator's truth), driven ``off_map`` (metres out, metres back) beyond its route and back,
    and ``kidnap`` (``AT_S:GAP_S``, ``AT_S:GAP_S:hidden`` with the clock's gap hidden too) as
    ``benchmarks/make_rosbag.py`` drives it."""
    from pnvlad_service.synth.generate import simulated_drive
    from pnvlad_service.synth.windows import drives_of

    spec, a, k, seed = drives_of(root)[(area, name)]
    if off_map:
        from pnvlad_service.synth.excursions import off_map_drive

        drive = off_map_drive(spec, a, k, seed, *off_map)
    else:
        drive = simulated_drive(spec, a, k, seed)
    if kidnap:
        from pnvlad_service.synth.excursions import Kidnapped

        at_s, gap_s, *hidden = kidnap.split(":")
        drive = Kidnapped(drive, float(at_s), float(gap_s), hide_gap=bool(hidden))
    return drive


def bag_of(root: Path, out: Path, area: str, name: str, every: int,
           off_map: tuple[float, float] | None = None,
           kidnap: str | None = None) -> tuple[Path, str, object]:  # fmt: skip
    """The run as a ROS 2 bag (written once), the --origin of its pose frame, the drive."""
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag

    drive = drive_of(root, area, name, off_map, kidnap)
    inner = drive
    while not hasattr(inner, "world"):
        inner = inner.drive
    east, north = (float(v) for v in inner.world.origin)
    bag = out / "bags" / area / f"{name}-{drive_name(every, off_map, kidnap)}"
    if not (bag / "metadata.yaml").is_file():
        bag.parent.mkdir(parents=True, exist_ok=True)
        sub = EveryNth(drive, every)
        write_drive_bag(sub, bag, origin_ne=(north, east), truth=sub.true, progress=False)
    return bag, f"{north!r},{east!r}", inner


def invoke(args: list[str], what: str):
    """``pnvlad ARGS`` in this process (the model and maps stay loaded); the logging the
    command set up on the runner's captured stderr is pointed back at ours afterwards (the
    runner closes that stream: later log lines would fail)."""
    from typer.testing import CliRunner

    from pnvlad_cli.common import setup_logging
    from pnvlad_cli.main import app

    res = CliRunner().invoke(app, args)
    setup_logging(0)  # the command's own set-up, on this process's stderr again
    if res.exit_code != 0:
        raise SystemExit(f"{what} failed:\n{res.output}")
    return res


def follow_run(root: Path, model: Path, out: Path, area: str, name: str, every: int,
               opts: argparse.Namespace | None = None) -> dict:  # fmt: skip
    """Map, bag and the followed drive of one run; its figures. ``opts``: the command's
    ``leave_one_out`` (the map aligned from the area's other recorded runs, the bag from the
    recorded run), ``off_map``, ``back``, ``kidnap``, ``extra`` (more ``pnvlad localize``
    options)."""
    from pnvlad_service.localization.drive.report import summarise
    from pnvlad_service.localization.drive.rows import read_rows

    opts = opts or argparse.Namespace()
    align_s = None
    if getattr(opts, "leave_one_out", False):
        from leave_one_out import aligned_without

        tree, align_s = aligned_without(root, opts.aligned or out, area, name, invoke)
        bundle = map_of(tree, model, out, area, name, tag=f"maps-loo/{model_tag(model)}")
    else:
        bundle = map_of(root, model, out, area, name, tag=f"maps/{model_tag(model)}")
    off_map = (opts.off_map, opts.back) if getattr(opts, "off_map", 0.0) else None
    kidnap = getattr(opts, "kidnap", None)
    if kidnap and getattr(opts, "hide_gap", False):
        kidnap += ":hidden"
    bag, origin, drive = bag_of(root, out, area, name, every, off_map, kidnap)
    protocol = "loo" if getattr(opts, "leave_one_out", False) else "shared"
    protocol += "-any-run" if getattr(opts, "aligned_map", False) else ""
    dest = (out / "replays" / f"{protocol}-{model_tag(model)}" / area
            / f"{name}-{drive_name(every, off_map, kidnap)}")  # fmt: skip
    dest.parent.mkdir(parents=True, exist_ok=True)
    args = ["localize", "--rosbag", str(bag), "--cloud-topic", "/points", "--pose-topic", "/odom",
            "--truth-topic", "/ground_truth", "--origin", origin, "--index", str(bundle),
            "-m", str(model), "--out", str(dest), "--no-progress",
            *(["--aligned-map"] if getattr(opts, "aligned_map", False) else []),
            *(getattr(opts, "extra", None) or [])]  # fmt: skip
    t0 = time.perf_counter()
    res = invoke(args, f"following {area}/{name}")
    wall = time.perf_counter() - t0
    s = summarise(read_rows(f"{dest}.csv"), "tracked", wall)
    return {"area": area, "run": name, "reverse": bool(drive.reverse), "summary": s,
            "align_s": align_s, "line": res.stdout.strip().splitlines()[-1]}  # fmt: skip


def per_scan_run(root: Path, model: Path, out: Path, area: str, name: str, every: int) -> dict:
    """The per-scan replay of one run: every ``every``-th scan asked alone."""
    bundle = map_of(root, model, out, area, name)
    bag, origin, _ = bag_of(root, out, area, name, every)
    dest = out / "replays" / area / f"{name}.per-scan"
    dest.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    args = ["localize", "--rosbag", str(bag), "--cloud-topic", "/points", "--per-scan",
            "--pose-topic", "/ground_truth", "--origin", origin, "--every", "1",
            "--index", str(bundle), "-m", str(model), "--out", str(dest),
            "--no-progress"]  # fmt: skip
    invoke(args, f"replay of {area}/{name}")
    seconds = time.perf_counter() - t0
    with open(f"{dest}.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    errors = np.array([float(r["error_m"]) for r in rows if r["error_m"]])
    ver = [r for r in rows if r["verified"] == "true"]
    pose_err = np.array([float(r["pose_error_m"]) for r in ver if r["pose_error_m"]])
    return {
        "area": area,
        "run": name,
        "queries": len(rows),
        "within": int((errors <= 25.0).sum()),
        "verified": len(ver),
        "median_pose_m": float(np.median(pose_err)) if len(pose_err) else float("nan"),
        "wrong_verified": int((pose_err > 5.0).sum()),
        "seconds": seconds,
    }


def _f(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


HEADER = (
    f"{'area':<12} {'run':<19} {'dir':<4} {'scans':>5} {'fix m':>6} {'fix s':>5} "
    f"{'verified':>8} {'1m/2deg':>7} {'med m':>6} {'p99 m':>6} {'map med':>7} {'map p99':>7} "
    f"{'>5 m':>4} {'reloc':>5} {'lost':>4} {'scan/s':>6}"
)


def row_line(f: dict) -> str:
    s = f["summary"]
    return (
        f"{f['area']:<12} {f['run']:<19} {'rev' if f['reverse'] else 'fwd':<4} {s.scans:>5} "
        f"{_f(s.first_fix_m, '.1f'):>6} {_f(s.first_fix_s, '.1f'):>5} "
        f"{_f(None if s.verified_share is None else 100 * s.verified_share, '.1f'):>8} "
        f"{_f(None if s.good_share is None else 100 * s.good_share, '.1f'):>7} "
        f"{_f(s.median_error_m, '.2f'):>6} {_f(s.p99_error_m, '.2f'):>6} "
        f"{_f(s.median_map_error_m, '.2f'):>7} {_f(s.p99_map_error_m, '.2f'):>7} "
        f"{_f(s.wrong, 'd'):>4} {s.relocalisations:>5} {s.lost:>4} {s.scans_per_s:>6.1f}"
    )


def parser() -> argparse.ArgumentParser:
    """The command's options."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, required=True, help="a pnvlad synth tree")
    ap.add_argument("--model", type=Path, required=True, help="a single-scan model")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument(
        "--every",
        type=int,
        default=None,
        help="every Nth scan of a run (default: every scan; 10 with --per-scan)",
    )
    ap.add_argument("--per-scan", action="store_true", help="ask with each scan alone")
    ap.add_argument("--area", action="append", help="only this area (repeatable)")
    ap.add_argument("--run", action="append", help="only this run (repeatable)")
    ap.add_argument(
        "--leave-one-out",
        action="store_true",
        help="--root is the recorded tree: each run is followed on a map aligned by 'pnvlad "
        "map align' from its area's other runs only (kept under --aligned)",
    )
    ap.add_argument(
        "--aligned-map",
        action="store_true",
        help="follow with 'pnvlad localize --aligned-map' (scans registered to the entries of "
        "any of the map's drives). Without it the follow does as the map's bundle records: a "
        "bundle built from an aligned tree (--leave-one-out, or a tree of pnvlad map align) "
        "records it",
    )
    ap.add_argument(
        "--aligned", type=Path, default=None, help="where the aligned trees go (default: --out)"
    )
    ap.add_argument(
        "--off-map",
        type=float,
        default=0.0,
        metavar="METRES",
        help="drive this far beyond each run's route (off the map) and back",
    )
    ap.add_argument(
        "--back",
        type=float,
        default=200.0,
        metavar="METRES",
        help="with --off-map: metres driven back along the route",
    )
    ap.add_argument(
        "--kidnap",
        default=None,
        metavar="AT_S:GAP_S",
        help="drop GAP_S seconds of scans from AT_S on (a kidnapped robot)",
    )
    ap.add_argument(
        "--hide-gap",
        action="store_true",
        help="with --kidnap: the clock does not jump over the gap either (only the scans tell)",
    )
    ap.add_argument(
        "--localize",
        dest="extra",
        action="append",
        default=[],
        metavar="OPTION",
        help="one more option for 'pnvlad localize' (repeatable: --localize=--radius "
        "--localize=30)",
    )
    return ap


def main() -> int:
    args = parser().parse_args()
    require("rosbags", "rosbags", "rosbag", "Replaying bags")

    from pnvlad_service.data.tree import BenchmarkTree

    every = args.every or (10 if args.per_scan else 1)
    tree = BenchmarkTree(args.root)
    names = [(a, n) for a in args.area or tree.datasets for n in tree.runs(a)
             if not args.run or n in args.run]  # fmt: skip
    if args.per_scan:
        return per_scan(args, names, every)
    print(HEADER, flush=True)
    figures = []
    for area, name in names:
        f = follow_run(args.root, args.model, args.out, area, name, every, args)
        figures.append(f)
        print(row_line(f), flush=True)
    runs = [f["summary"] for f in figures]
    fixed = [s for s in runs if s.first_fix_scan is not None]
    after = sum(round(s.verified_share * (s.scans - s.first_fix_scan // every)) for s in fixed)
    scans_after = sum(s.scans - s.first_fix_scan // every for s in fixed)
    good = sum(round((s.good_share or 0) * (s.scans - s.first_fix_scan // every)) for s in fixed)
    print(
        f"all {len(runs)} runs: {len(fixed)} with a fix, the farthest first fix "
        f"{max((s.first_fix_m or 0.0) for s in fixed) if fixed else float('nan'):.1f} m; "
        f"{100 * after / max(scans_after, 1):.1f} % of the {scans_after} scans after the fixes "
        f"verified, {100 * good / max(scans_after, 1):.1f} % within 1 m and 2 deg; "
        f"{sum(s.wrong or 0 for s in runs)} verified poses more than 5 m off; worst p99 error "
        f"{max((s.p99_error_m or 0.0) for s in runs):.2f} m; "
        f"{sum(s.relocalisations for s in runs)} relocalisations, {sum(s.lost for s in runs)} "
        "losses"
    )
    return 0


def per_scan(args: argparse.Namespace, names: list[tuple[str, str]], every: int) -> int:
    figures = []
    for area, name in names:
        f = per_scan_run(args.root, args.model, args.out, area, name, every)
        figures.append(f)
        print(
            f"{area:<12} {name}  {f['within']:3d}/{f['queries']:3d} within 25 m, "
            f"{f['verified']:3d} verified, verified poses {f['median_pose_m']:.2f} m "
            f"(median), {f['wrong_verified']} more than 5 m off; {f['seconds']:.0f} s",
            flush=True,
        )
    q = sum(f["queries"] for f in figures)
    within = sum(f["within"] for f in figures)
    ver = sum(f["verified"] for f in figures)
    wrong = sum(f["wrong_verified"] for f in figures)
    med = float(np.median([f["median_pose_m"] for f in figures]))
    print(
        f"all {len(figures)} runs: {within}/{q} within 25 m ({100 * within / q:.1f} %), {ver} "
        f"verified ({100 * ver / q:.1f} %), {wrong} verified poses more than 5 m off; median of "
        f"the runs' median pose errors {med:.2f} m"
    )
    return 0


if __name__ == "__main__":
    run(main)
