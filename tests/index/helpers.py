"""Test helpers shared by the index, server and localisation tests: a tiny benchmark tree, a
small random model, a free TCP port and a submap reader."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np

RUNS = ("2014-05-19-13-20-57", "2014-06-26-09-24-58")
PER_RUN = 16


def make_tree(root: Path, runs: tuple[str, ...] = RUNS, per_run: int = PER_RUN) -> Path:
    """A benchmark tree: ``oxford/<run>/pointcloud_20m/<ts>.bin`` + CSV. Run k's submap i is
    run 0's submap i plus 0.01 noise, so the places repeat across runs."""
    rng = np.random.default_rng(7)
    base = rng.uniform(-0.9, 0.9, (per_run, 4096, 3))
    for r, run in enumerate(runs):
        folder = root / "oxford" / run / "pointcloud_20m"
        folder.mkdir(parents=True)
        lines = ["timestamp,northing,easting"]
        for i in range(per_run):
            ts = 1_400_000_000_000_000 + 1_000_000 * (1000 * r + i)
            pts = base[i] + (0.01 * rng.standard_normal((4096, 3)) if r else 0.0)
            pts.clip(-1, 1).astype("<f8").tofile(folder / f"{ts}.bin")
            lines.append(f"{ts},{5735000.0 + 20.0 * i + 0.25 * r},{620000.0 + 1.5 * r}")
        (folder.parent / "pointcloud_locations_20m.csv").write_text("\n".join(lines) + "\n")
    return root


def make_checkpoint(path: Path, seed: int = 0) -> Path:
    """A small randomly initialised PointNetVLAD (16-d descriptors) saved as a checkpoint."""
    import torch

    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.pointnetvlad import build_model
    from pnvlad_service.models.store import save_model

    torch.manual_seed(seed)
    cfg = ModelConfig.compact(
        stem_widths=(8, 8),
        trunk_widths=(16, 32),
        tnet_point_widths=(8, 16),
        tnet_fc_widths=(16, 8),
        cluster_size=4,
        output_dim=16,
    )
    model = build_model(cfg)
    # Non-trivial batch-norm statistics, so folding them is exercised.
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return save_model(path, model, cfg)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def read_cloud(root: Path, rel: str) -> np.ndarray:
    return np.fromfile(root / rel, dtype="<f8").reshape(-1, 3)
