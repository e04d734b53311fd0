"""ONNX Runtime against torch, in one run: each encoder's ms per cloud and clouds/s at batch 1
and 32 on the same threads, the two runtimes timed in alternation round after round (a shared
machine's drift weighs on both alike; each figure the fastest of its rounds), and the ratio.
Optionally, with trained weights and a benchmark tree, whether both runtimes give the same
top-1 on its submaps (leave-one-out nearest neighbour among them) and how far apart their
descriptors are.

The models are random weights of the shipped configurations (``paper``: PN_VLAD, ``compact``,
``bev``: bev-netvlad; ``--heading`` adds canonical heading), exported with ``pnvlad model
export`` into a temporary directory; ``--model DIR`` times a trained model instead (exported
beside its weights when it has no model.onnx yet). Clouds: seeded street-like clouds of 4096
points (``onnx_encoder.check_clouds``).

    python benchmarks/bench_runtime.py --threads 2                 # paper and bev, batch 1, 32
    python benchmarks/bench_runtime.py --threads 2 --configs paper,compact,bev --rounds 7
    python benchmarks/bench_runtime.py --model runs/r40/model --root city --count 1000
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from entry import run

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import Encoder, other_distances
from pnvlad_service.models.onnx_encoder import ONNX_FILE, OnnxEncoder, check_clouds, cosines
from pnvlad_service.models.onnx_export import export_onnx
from pnvlad_service.models.store import save_model


def fastest(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def model_dir(name: str, heading: bool, work: Path, point_tile: int) -> Path:
    """A random-weight model of configuration ``name`` saved and exported under ``work``."""
    torch.manual_seed(0)
    cfg = getattr(ModelConfig, name)(canonical_heading=heading)
    d = work / f"{name}{'-heading' if heading else ''}"
    save_model(d, build_model(cfg).eval(), cfg)
    export_onnx(d, point_tile=point_tile)
    return d


def compare_speed(
    label: str, directory: Path, threads: int, batches: list[int], rounds: int
) -> list[dict]:
    """Both runtimes on ``directory``'s model, alternated ``rounds`` times per batch size."""
    torch_enc = Encoder.from_checkpoint(directory)
    onnx_enc = OnnxEncoder.from_checkpoint(directory, threads=threads)
    x = check_clouds(7, max(batches), 4096)
    rows = []
    for b in batches:
        xb = x[:b]
        for enc in (torch_enc, onnx_enc):  # first pass of each shape
            enc.embed(xb)
        best = {"torch": float("inf"), "onnx": float("inf")}
        for r in range(rounds):
            order = [("torch", torch_enc), ("onnx", onnx_enc)]
            for name, enc in order if r % 2 == 0 else order[::-1]:
                best[name] = min(best[name], fastest(lambda e=enc, x=xb: e.embed(x)))
        row = {
            "model": label,
            "batch": b,
            **{f"{k}_ms": 1000 * v / b for k, v in best.items()},
            **{f"{k}_cps": b / v for k, v in best.items()},
        }
        row["onnx_vs_torch"] = best["torch"] / best["onnx"]
        rows.append(row)
        print(
            f"{label:>16} {b:>5} {row['torch_ms']:>9.2f} {row['onnx_ms']:>9.2f} "
            f"{row['torch_cps']:>10.1f} {row['onnx_cps']:>10.1f} {row['onnx_vs_torch']:>8.2f}x "
            f"{'(ONNX Runtime faster)' if row['onnx_vs_torch'] > 1 else ''}",
            flush=True,
        )
    torch_enc.close()
    onnx_enc.close()
    return rows


def agreement(directory: Path, root: Path, count: int, threads: int) -> None:
    """Top-1 (leave-one-out) of both runtimes on ``count`` test-layout submaps of ``root``."""
    from pnvlad_service.index.build import list_database_submaps
    from pnvlad_service.io.readers import read_points

    records = list_database_submaps(root)[:count]
    clouds = np.stack([read_points(root / r.path, "benchmark") for r in records]).astype(np.float32)
    t = Encoder.from_checkpoint(directory).embed(clouds)
    o = OnnxEncoder.from_checkpoint(directory, threads=threads).embed(clouds)
    cos = cosines(t, o)
    top_t, top_o = other_distances(t).argmin(1), other_distances(o).argmin(1)
    same = int((top_t == top_o).sum())
    print(
        f"{len(records)} submaps of {root}: the same top-1 for {same} "
        f"({100 * same / len(records):.2f} %); descriptor cosine min {cos.min():.7f}, "
        f"median {np.median(cos):.7f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--threads", type=int, default=2, help="torch's and ONNX Runtime's threads.")
    ap.add_argument("--configs", default="paper,bev", help="Shipped configurations, comma list.")
    ap.add_argument("--heading", action="store_true", help="With canonical heading on.")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    ap.add_argument("--rounds", type=int, default=5, help="Alternations per batch size.")
    ap.add_argument("--point-tile", type=int, default=512, help="The export's point tile.")
    ap.add_argument("--model", type=Path, help="A trained model directory instead.")
    ap.add_argument("--root", type=Path, help="A benchmark tree: the top-1 agreement check.")
    ap.add_argument("--count", type=int, default=1000, help="Submaps of --root checked.")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"torch {torch.__version__}, onnxruntime {__import__('onnxruntime').__version__}, "
        f"{args.threads} threads"
    )
    print(
        f"{'model':>16} {'batch':>5} {'torch ms':>9} {'onnx ms':>9} {'torch c/s':>10} "
        f"{'onnx c/s':>10} {'onnx/torch':>9}"
    )
    with tempfile.TemporaryDirectory(prefix="pnvlad-bench-runtime-") as tmp:
        if args.model is not None:
            if not (args.model / ONNX_FILE).is_file():
                export_onnx(args.model, point_tile=args.point_tile)
            dirs = {args.model.name: args.model}
        else:
            dirs = {
                name + ("+heading" if args.heading else ""): model_dir(
                    name, args.heading, Path(tmp), args.point_tile
                )
                for name in args.configs.split(",")
            }
        for label, d in dirs.items():
            compare_speed(label, d, args.threads, args.batches, args.rounds)
        if args.root is not None:
            for d in dirs.values():
                agreement(d, args.root, args.count, args.threads)


if __name__ == "__main__":
    run(main)
