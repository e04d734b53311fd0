"""The shipped models on real spinning-sensor scans: KITTI 00's revisit and consecutive frames.

Six real KITTI scans lie in the shared real-scan folder (``$PNVLAD_REAL_SCANS``, else
``../shared/data/real_scans`` beside the checkout; see its README): frames 52 and 4501 of
sequence 00 (the same street about 3 m apart, 7.5 minutes apart: a real revisit), frames 94
and 95 (0.47 m apart) and two scans of another drive. Each is read as a raw scan and put
through the filter G as a single scan is (``filter_g.scan_config``: the 50 m disc, ground
removed, 4,096 points), then embedded by each model. Two queries: 4501 (its place: 52) and
95 (its place: 94), each against the other five scans. Per model and query: the rank of its
place among the five (1 = found), the descriptor distance to it and to the nearest other
scan, and their ratio (under 1: the place is nearer than anything else).

A handful of scans, not a recall figure: it says whether a model trained on synthetic
cities tells a real revisit from real other streets. Each model is also measured with the
same network's random weights (seed 0), the floor a trained model must rise above: with four
distractors the rank alone does not tell them apart, the ratio does (random bev-netvlad
weights give nearly one descriptor for every cloud, distances near 0).

    python benchmarks/kitti_frames.py [--model MODEL ...] [--scans DIR]

Without ``--model``: every pretrained model that ships (``pnvlad model list``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import real_scans_default, run

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_scan
from pnvlad_service.preprocess.filter_g import filter_g, scan_config

FRAMES = (0, 5, 52, 94, 95, 4501)
FILES = {f: f"kitti00_{f:06d}.bin" for f in FRAMES}
#: query frame -> the frame of its place
QUERIES = {4501: 52, 95: 94}


def scans_dir(given: Path | None) -> Path:
    """The real-scan folder: ``given``, else :func:`entry.real_scans_default`."""
    folder = given or Path(real_scans_default())
    missing = [name for name in FILES.values() if not (folder / name).is_file()]
    if missing:
        raise InputError(f"no {missing[0]} here (the real KITTI scans)", folder)
    return folder


def clouds(folder: Path) -> np.ndarray:
    """The six scans through G as single scans: float32 [6, 4096, 3], in FRAMES order."""
    cfg = scan_config()
    out = []
    for frame in FRAMES:
        points, _ = read_scan(folder / FILES[frame], "kitti")
        out.append(filter_g(points, cfg))
    return np.stack(out).astype(np.float32)


def rows(desc: np.ndarray) -> list[tuple[int, int, float, float]]:
    """Per query: (frame, rank of its place among the others, distance to it, nearest other)."""
    out = []
    for query, place in QUERIES.items():
        qi = FRAMES.index(query)
        others = [i for i in range(len(FRAMES)) if i != qi]
        d = {i: float(np.linalg.norm(desc[qi] - desc[i])) for i in others}
        order = sorted(others, key=lambda i: d[i])
        pi = FRAMES.index(place)
        nearest_other = min(d[i] for i in others if i != pi)
        out.append((query, order.index(pi) + 1, d[pi], nearest_other))
    return out


def random_twin(model: str, tmp: Path) -> Path:
    """The model's network with random weights (torch seed 0), saved under ``tmp``."""
    import torch

    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import read_model_json, save_model

    cfg, _ = read_model_json(model)
    torch.manual_seed(0)
    return save_model(tmp / "random", build_model(cfg), cfg)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--model", action="append", help="a model (default: every shipped one)")
    ap.add_argument("--scans", type=Path, help="the real-scan folder")
    args = ap.parse_args()
    from pnvlad_service.models.pretrained import Catalogue
    from pnvlad_service.models.runtimes import load_encoder

    models = args.model or [f"pretrained:{n}" for n in Catalogue.read().names]
    x = clouds(scans_dir(args.scans))
    print("model                            weights  query  place rank  d(place)  d(other)  ratio")
    for model in models:
        with tempfile.TemporaryDirectory() as tmp:
            for label, path in (("trained", model), ("random", random_twin(model, Path(tmp)))):
                enc = load_encoder(path)
                desc = enc.embed(x)
                for query, rank, d_place, d_other in rows(desc):
                    print(
                        f"{model:32s} {label:8s} {query:5d}  {rank:10d}  {d_place:8.2g}  "
                        f"{d_other:8.2g}  {d_place / d_other:5.2f}"
                    )
    return 0


if __name__ == "__main__":
    run(main)
