"""Registration back-ends compared on pairs with a known transform (issue #10): our
pnvlad_service.localization.verify.registration with small_gicp GICP and VGICP, kiss-icp's
point-to-point ICP and open3d's point-to-plane ICP and GICP, all started from the same yaw
search so that only the local registration differs; plus false pairs for the score.

    python benchmarks/registration.py [--pairs N] [--threads 2] [--kiss DIR] [--open3d DIR]

Pairs: submaps of two synthetic runs passing the same place (query turned by a random yaw,
offset up to 10 m along the road), raw single scans through G against a submap, and
unrelated submaps (>= 60 m apart) as false pairs. kiss-icp and open3d are optional; install
them outside the project (``pip install --target DIR kiss-icp``, open3d likewise: 400 MB) and
pass DIR. Prints one table: success (< 2 m and < 5 degrees), median errors, fitness of true and
false pairs, ms per pair and per 10 candidates including prepare.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import run

from pnvlad_service.localization.verify import registration as reg
from tests.localization import submap_pairs as sp

CACHE = Path("/tmp/pnvlad_registration_pairs.npz")


def errors(estimate: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error degrees) of ``estimate`` against ``true``."""
    e = np.linalg.inv(true) @ estimate
    angle = np.linalg.norm(Rotation.from_matrix(e[:3, :3]).as_rotvec())
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(angle))


def make_pairs(n: int, seed: int = 3) -> dict[str, list[sp.Pair]]:
    """``n`` submap pairs, ``n // 2`` scan pairs and ``n // 2`` false pairs (cached)."""
    rng = np.random.default_rng(seed)
    ds = sp.drives()
    runs = [(0, 1), (0, 2), (1, 2), (1, 0), (2, 0)]
    out: dict[str, list[sp.Pair]] = {"submap": [], "scan": [], "false": []}
    for k in range(n):
        a, b = runs[k % len(runs)]
        i = int(rng.integers(4, len(ds[a]) - 4))
        offset, yaw = rng.uniform(0, 10), rng.uniform(0, 2 * np.pi)
        out["submap"].append(sp.submap_pair(ds[a], ds[b], i, offset, yaw))
        if k % 2 == 0:
            out["scan"].append(sp.scan_pair(ds[a], ds[b], i, rng.uniform(0, 8)))
            far = sp.submap_pair(ds[a], ds[b], (i + 20) % len(ds[a]), 0.0, yaw)
            out["false"].append(sp.Pair(far.source, sp.submap(ds[a], i)[0], far.truth, "false"))
    return out


def load_pairs(n: int) -> dict[str, list[sp.Pair]]:
    if CACHE.exists():
        z = np.load(CACHE, allow_pickle=False)
        if int(z["n"]) == n:
            return {
                kind: [
                    sp.Pair(z[f"{kind}{k}s"], z[f"{kind}{k}t"], z[f"{kind}{k}T"], kind)
                    for k in range(int(z[f"{kind}_count"]))
                ]
                for kind in ("submap", "scan", "false")
            }
    pairs = make_pairs(n)
    arrays: dict[str, np.ndarray] = {"n": np.array(n)}
    for kind, items in pairs.items():
        arrays[f"{kind}_count"] = np.array(len(items))
        for k, p in enumerate(items):
            arrays[f"{kind}{k}s"], arrays[f"{kind}{k}t"], arrays[f"{kind}{k}T"] = (
                p.source,
                p.target,
                p.truth,
            )
    np.savez(CACHE, **arrays)
    return pairs


# --- back-ends: (prepared source, prepared target, start 4x4) -> 4x4 -------------------------

Refine = Callable[[reg.Prepared, reg.Prepared, np.ndarray], np.ndarray]


def ours(config: reg.RegistrationConfig) -> Callable[[sp.Pair], tuple[np.ndarray, float, float]]:
    """The module as the service calls it: prepare both, register from the yaw search."""

    def run(pair: sp.Pair) -> tuple[np.ndarray, float, float]:
        t0 = time.perf_counter()
        src, tgt = reg.prepare(pair.source, config), reg.prepare(pair.target, config)
        t1 = time.perf_counter()
        result = reg.register(src, tgt, config)
        t2 = time.perf_counter()
        return result.transform, result.fitness, (t1 - t0, t2 - t1)  # type: ignore[return-value]

    return run


def kiss_refine(directory: str, threads: int) -> Refine:
    sys.path.insert(0, directory)
    from kiss_icp.pybind import kiss_icp_pybind as k

    def refine(src: reg.Prepared, tgt: reg.Prepared, start: np.ndarray) -> np.ndarray:
        vm = k._VoxelHashMap(voxel_size=1.0, max_distance=200.0, max_points_per_voxel=20)
        vm._add_points(k._Vector3dVector(tgt.points))
        icp = k._Registration(
            max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=threads
        )
        return np.asarray(
            icp._align_points_to_map(
                points=k._Vector3dVector(src.points),
                voxel_map=vm,
                initial_guess=_orthonormal(start),
                max_correspondance_distance=3.0,
                kernel=1.0,
            )
        )

    return refine


_OPEN3D: dict[str, object] = {}


def _open3d(directory: str) -> object:
    """open3d's core extension, loaded once without the package's GUI dependencies."""
    if "core" not in _OPEN3D:
        so = next(Path(directory, "open3d").glob("pybind*.so"))
        spec = importlib.util.spec_from_file_location("pybind", so)
        module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
        spec.loader.exec_module(module)  # type: ignore[union-attr]
        _OPEN3D["core"] = module
    return _OPEN3D["core"]


def open3d_refine(directory: str, kind: str) -> Refine:
    o3: Any = _open3d(directory)
    r = o3.pipelines.registration

    def cloud(points: np.ndarray) -> object:
        pc = o3.geometry.PointCloud()
        pc.points = o3.utility.Vector3dVector(points)
        pc.estimate_normals(o3.geometry.KDTreeSearchParamKNN(10))
        return pc

    def refine(src: reg.Prepared, tgt: reg.Prepared, start: np.ndarray) -> np.ndarray:
        a, b = cloud(src.points), cloud(tgt.points)
        crit = r.ICPConvergenceCriteria(max_iteration=30)
        if kind == "plane":
            est = r.registration_icp(
                a, b, 1.0, start, r.TransformationEstimationPointToPlane(), crit
            )
        else:
            est = r.registration_generalized_icp(
                a, b, 1.0, start, r.TransformationEstimationForGeneralizedICP(), crit
            )
        return np.asarray(est.transformation)

    return refine


def _orthonormal(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m[:3, :3])
    out = np.array(m, dtype=np.float64)
    out[:3, :3] = u @ vt
    return out


def external(refine: Refine, config: reg.RegistrationConfig) -> Callable:
    """Another library's local registration from our coarse start (yaw search + coarse GICP
    stage replaced by the yaw search alone), fitness by our definition."""

    def run(pair: sp.Pair) -> tuple[np.ndarray, float, tuple[float, float]]:
        t0 = time.perf_counter()
        src, tgt = reg.prepare(pair.source, config), reg.prepare(pair.target, config)
        t1 = time.perf_counter()
        yaws = reg.yaw_candidates(src, tgt, config)
        placed = max(reg.place(src, tgt, yaws, config), key=lambda p: p[1])
        transform = refine(src, tgt, placed[0])
        fit, _ = reg.fitness(src.points, tgt, transform, config.inlier_m, config.threads)
        return transform, fit, (t1 - t0, time.perf_counter() - t1)

    return run


def evaluate(name: str, run: Callable, pairs: dict[str, list[sp.Pair]]) -> str:
    rows, prep, regt, fits = [], [], [], {}
    for kind in ("submap", "scan"):
        for p in pairs[kind]:
            transform, fit, (tp, tr) = run(p)
            rows.append((*errors(transform, p.truth), fit))
            prep.append(tp)
            regt.append(tr)
        fits[kind] = [r[2] for r in rows[-len(pairs[kind]) :]]
    false = [run(p)[1] for p in pairs["false"]]
    e = np.array(rows)
    ok = (e[:, 0] < 2.0) & (e[:, 1] < 5.0)
    med_prep, med_reg = 1e3 * np.median(prep) / 2, 1e3 * np.median(regt)
    per10 = med_prep + 10 * (med_prep + med_reg)  # query once, each candidate prepared + registered
    return (
        f"| {name} | {ok.mean():.0%} | {np.median(e[ok, 0]):.3f} | {np.median(e[ok, 1]):.2f} | "
        f"{np.median(fits['submap']):.2f} / {np.median(fits['scan']):.2f} | {max(false):.2f} | "
        f"{med_prep:.1f} | {med_reg:.1f} | {per10:.0f} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--kiss", help="folder holding kiss_icp (pip install --target)")
    ap.add_argument("--open3d", help="folder holding open3d (pip install --target)")
    ap.add_argument("--only-ours", action="store_true")
    args = ap.parse_args()
    pairs = load_pairs(args.pairs)
    cfg = replace(reg.DEFAULT, threads=args.threads)
    print(
        f"{len(pairs['submap'])} submap pairs, {len(pairs['scan'])} scan pairs, "
        f"{len(pairs['false'])} false pairs; {args.threads} threads\n"
    )
    print(
        "| back-end | success | median t err m | median rot err deg | fitness true submap/scan "
        "| max fitness false | prepare ms | register ms | 10 candidates ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print(evaluate("small_gicp VGICP (ours, default)", ours(cfg), pairs), flush=True)
    print(evaluate("small_gicp GICP (ours)", ours(replace(cfg, method="GICP")), pairs))
    if args.only_ours:
        return 0
    if args.kiss:
        print(
            evaluate("kiss-icp p2p ICP", external(kiss_refine(args.kiss, args.threads), cfg), pairs)
        )
    if args.open3d:
        for kind in ("plane", "gicp"):
            run = external(open3d_refine(args.open3d, kind), cfg)
            print(evaluate(f"open3d {kind} ICP", run, pairs))
    return 0


if __name__ == "__main__":
    run(main)
