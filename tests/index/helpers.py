"""Test helpers shared by the index, server and localisation tests: a tiny benchmark tree, a
small random model, the two with their bundle, a free TCP port and a submap reader."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np

RUNS = ("2014-05-19-13-20-57", "2014-06-26-09-24-58")
PER_RUN = 16


def make_tree(
    root: Path,
    runs: tuple[str, ...] = RUNS,
    per_run: int = PER_RUN,
    frames: bool | tuple[str, ...] = False,
) -> Path:
    """A benchmark tree: ``oxford/<run>/pointcloud_20m/<ts>.bin`` + CSV. Run k's submap i is
    run 0's submap i plus 0.01 noise, so the places repeat across runs.

    ``frames``: write each run's frame sidecar (``True``) or those of the runs named
    (:func:`sidecar_frames`: origin at the submap's easting/northing, a centre of a few metres,
    scales of 20-60 m, every third one negative)."""
    from pnvlad_service.data.frames import frames_path, write_frames_csv

    with_frames = set(runs if frames is True else (frames or ()))
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
        csv = folder.parent / "pointcloud_locations_20m.csv"
        csv.write_text("\n".join(lines) + "\n")
        if run in with_frames:
            write_frames_csv(frames_path(csv), sidecar_frames(csv))
    return root


def sidecar_frames(csv: Path):
    """Frame sidecar rows for the locations CSV ``csv`` (see :func:`make_tree`)."""
    from pnvlad_service.data.frames import SubmapFrame
    from pnvlad_service.data.tree import read_locations_csv

    loc = read_locations_csv(csv)
    out = []
    for i, (ts, n, e) in enumerate(loc.rows()):
        rng = np.random.default_rng(ts % 2**32)
        scale = (20.0 + 40.0 * rng.random()) * (-1.0 if i % 3 == 2 else 1.0)
        origin = np.array([e, n, 60.0 + rng.random()])
        out.append(SubmapFrame(ts, origin, rng.uniform(-5, 5, 3), scale))
    return out


def make_checkpoint(path: Path, seed: int = 0, canonical_heading: bool = False) -> Path:
    """A small randomly initialised PointNetVLAD (16-d descriptors) saved as a checkpoint;
    ``canonical_heading``: one that turns clouds to their own heading (maps of 4 headings)."""
    import torch

    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import save_model

    torch.manual_seed(seed)
    cfg = ModelConfig.compact(
        stem_widths=(8, 8),
        trunk_widths=(16, 32),
        tnet_point_widths=(8, 16),
        tnet_fc_widths=(16, 8),
        cluster_size=4,
        output_dim=16,
        canonical_heading=canonical_heading,
    )
    model = build_model(cfg)
    # Non-trivial batch-norm statistics, so folding them is exercised.
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return save_model(path, model, cfg)


def make_world(base: Path, bundle_name: str = "map.index", frames: bool = False) -> dict[str, Path]:
    """Under ``base``: ``tree`` (:func:`make_tree`; ``frames``: with frame sidecars, so the
    bundle has geometry), ``ckpt`` (:func:`make_checkpoint`) and ``bundle``, a Flat bundle of
    the tree built with that model; the paths, and ``base``."""
    from pnvlad_service.index.build import build_bundle

    tree = make_tree(base / "tree", frames=frames)
    ckpt = make_checkpoint(base / "ckpt")
    bundle = base / bundle_name
    build_bundle(bundle, ckpt, tree, progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "bundle": bundle}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def read_cloud(root: Path, rel: str) -> np.ndarray:
    return np.fromfile(root / rel, dtype="<f8").reshape(-1, 3)
