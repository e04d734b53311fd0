"""Tuple training (the paper) against in-batch mining, for the same wall-clock budget.

Builds a small synthetic tree (the generator of tests/training/street.py: a street of box-shaped
landmarks driven ``--runs`` times), trains the same small network for ``--minutes`` with each
mining mode, evaluates each final model (and the untrained one) with the benchmark's recall and
prints one line per mode. On a shared CPU the figures are noisy: compare modes of one run.

    python benchmarks/bench_mining.py --minutes 3
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

from entry import run

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--minutes", type=float, default=3.0, help="budget of each mode")
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--num-points", type=int, default=512)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--keep", type=Path, default=None, help="keep the tree and runs here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sys.path.insert(0, str(REPO))
    import torch

    from pnvlad_service.data.dataset import load_eval_runs
    from pnvlad_service.evaluation.evaluate import evaluate_runs
    from pnvlad_service.models.embedding import module_embedder
    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import load_model
    from pnvlad_service.training.config import TrainConfig
    from pnvlad_service.training.train import train
    from tests.training.street import make_tiny_tree  # the tests' synthetic street

    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="pnvlad-mining-") as tmp:
        root = args.keep or Path(tmp)
        splits = make_tiny_tree(root / "tree", runs=args.runs)
        runs = load_eval_runs(root / "tree", splits)
        base = TrainConfig.from_mapping(
            {
                "model": {"preset": "compact", "num_points": args.num_points},
                "train": {
                    "lr": 1e-3,
                    "epochs": 1000,
                    "max_minutes": args.minutes,
                    "cache_warmup_epochs": 1,
                    "cache_refresh_steps": 50,
                    "sampled_negatives": 200,
                    "val_every": 0,
                    "checkpoint_every": 10**6,
                    "threads": args.threads,
                },
                "data": {"root": str(root / "tree"), "splits": str(splits)},
            }
        )
        torch.manual_seed(0)
        untrained = build_model(base.model)
        rep = evaluate_runs(module_embedder(untrained), runs, args.num_points, progress=False)
        print(f"untrained: recall@1 {rep['recall_at_1']:.1f}, @1% {rep['recall_at_1pct']:.1f}")
        for mode, batch in (("tuple", 4), ("in_batch", 16)):
            cfg = base.with_overrides({"train.mining": mode, "train.batch_size": batch})
            t0 = time.monotonic()
            res = train(cfg, root / f"run-{mode}", progress=False)
            secs = time.monotonic() - t0
            model, _ = load_model(res.model_dir)
            rep = evaluate_runs(module_embedder(model), runs, args.num_points, progress=False)
            print(
                f"{mode:9s}: {res.steps} steps in {secs:.0f} s, cache refreshes "
                f"{res.cache_refreshes}, last loss {res.losses[res.steps]:.3f}; "
                f"recall@1 {rep['recall_at_1']:.1f}, @1% {rep['recall_at_1pct']:.1f}"
            )


if __name__ == "__main__":
    run(main)
