"""Training checkpoints: a model directory (``models/store.py``) plus the training state.

Layout under a run's output directory::

    OUT/checkpoints/step-00001200/  model.safetensors, model.json   (models/store.py)
                                    train_state.pt   tensors only: optimiser, grad scaler, torch
                                                     RNG states, descriptor cache
                                    train.json       step, epoch, sampler and NumPy RNG states,
                                                     the full TrainConfig, elapsed seconds
    OUT/checkpoints/latest          name of the newest complete checkpoint
    OUT/model/                      the final model (models/store.py), for eval / index / serve

Each checkpoint directory appears atomically (``atomic_directory``) and ``latest`` is rewritten
atomically after it, so a run killed at any moment leaves the previous checkpoint usable.
``train_state.pt`` is read with ``torch.load(weights_only=True)``: no pickled code runs.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_directory, atomic_write_text

if TYPE_CHECKING:
    import torch

    from pnvlad_service.models.config import ModelConfig

log = logging.getLogger(__name__)

FORMAT = "pnvlad-train"
VERSION = 1
STATE_FILE = "train_state.pt"
JSON_FILE = "train.json"
LATEST = "latest"


@dataclass
class TrainingState:
    """What a resumed run needs besides the weights.

    ``tensors``: name -> tensor or nested dict/list of tensors and numbers (optimiser and scaler
    state dicts, torch RNG states as uint8 tensors, the descriptor cache float32 [N, D]).
    ``info``: JSON-serialisable (step, epoch, sampler state, NumPy bit-generator states, config).
    """

    tensors: dict[str, Any]
    info: dict[str, Any]


def checkpoint_dir(out: str | Path, step: int) -> Path:
    return Path(out) / "checkpoints" / f"step-{step:08d}"


def save_checkpoint(
    out: str | Path,
    step: int,
    model: torch.nn.Module,
    cfg: ModelConfig,
    state: TrainingState,
    *,
    keep: int = 2,
) -> Path:
    """Write ``OUT/checkpoints/step-<step>`` atomically, point ``latest`` at it and keep only the
    newest ``keep`` step checkpoints. Returns the checkpoint directory."""
    import torch

    from pnvlad_service.models.store import write_model_files

    path = checkpoint_dir(out, step)
    info = {"format": FORMAT, "version": VERSION, "step": step, **state.info}
    with atomic_directory(path, overwrite=True) as tmp:
        write_model_files(tmp, model, cfg, {"source": "pnvlad train", "step": step})
        torch.save(state.tensors, tmp / STATE_FILE)
        (tmp / JSON_FILE).write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    atomic_write_text(path.parent / LATEST, path.name + "\n")
    old = sorted(p for p in path.parent.glob("step-*") if p.is_dir())
    for p in old[:-keep]:
        shutil.rmtree(p, ignore_errors=True)
    log.debug("checkpoint written: %s", path)
    return path


def latest_checkpoint(out: str | Path) -> Path | None:
    """The newest complete checkpoint under ``OUT`` (or ``OUT`` itself if it is one), or None."""
    out = Path(out)
    if (out / JSON_FILE).is_file():
        return out
    pointer = out / "checkpoints" / LATEST
    if pointer.is_file():
        p = out / "checkpoints" / pointer.read_text(encoding="utf-8").strip()
        if (p / JSON_FILE).is_file():
            return p
    return None


def load_checkpoint(path: str | Path) -> tuple[dict[str, Any], TrainingState, Any]:
    """Read a training checkpoint: (model state dict, training state, its ModelConfig).

    Raises :class:`InputError` for a directory that is not a complete training checkpoint.
    """
    import torch
    from safetensors.torch import load_file

    from pnvlad_service.models.store import WEIGHTS_FILE, read_model_json

    path = Path(path)
    jpath = path / JSON_FILE
    if not jpath.is_file():
        raise InputError(f"not a training checkpoint (no {JSON_FILE})", path)
    try:
        info = json.loads(jpath.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc}", jpath) from None
    if info.get("format") != FORMAT or info.get("version") != VERSION:
        raise InputError(f"not a {FORMAT} v{VERSION} file", jpath)
    cfg, _ = read_model_json(path)
    weights = load_file(str(path / WEIGHTS_FILE), device="cpu")
    try:
        tensors = torch.load(path / STATE_FILE, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise InputError(f"no {STATE_FILE} in this checkpoint", path) from None
    return weights, TrainingState(tensors=tensors, info=info), cfg
