"""What a training run works on and what it carries from step to step.

- :class:`TrainData` and :func:`prepare_data`: the training set, its anchors, the clouds in RAM
  and the tuple's negatives fitted to the set; every check that the data can feed the configured
  steps happens here, before anything is written.
- :class:`TrainState` and :func:`build_state`: the model, optimiser, grad scaler, anchor order,
  tuple RNG and descriptor cache at step 0.
- :func:`checkpoint_to_resume`, :func:`resume_state` and :func:`save_state`: the state to and
  from the checkpoints of ``checkpoint.py``, so that a resumed run continues step for step.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun, TrainingSet, load_clouds
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.models.local_shape import shape_feature_fn
from pnvlad_service.training import mining
from pnvlad_service.training.checkpoint import (
    TrainingState,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from pnvlad_service.training.config import TrainConfig
from pnvlad_service.training.runtime import Runtime, restore_rng_state, rng_state_tensors

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)


@dataclass
class TrainData:
    """What the steps draw from: the training set, its ``anchors`` (int64), every training
    cloud in RAM (``clouds`` float32 [N, P, 3], pinned on CUDA), the validation runs and the
    negatives a tuple takes (``negatives``, ``hard_negatives``: the config's, or fewer on a
    training set too small for them, see :func:`mining.fit_negatives`)."""

    training_set: TrainingSet
    anchors: np.ndarray
    clouds: torch.Tensor
    val_runs: list[EvalRun]
    negatives: int
    hard_negatives: int


@dataclass
class TrainState:
    """Everything a step changes, and a checkpoint saves: the model (``net`` is its DDP
    wrapper, or the model itself alone), optimiser, grad scaler, anchor order, tuple RNG, the
    descriptor cache (float32 [N, D] or None) and the counters. ``saved_step``: the step of the
    newest checkpoint on disk (not saved itself)."""

    model: torch.nn.Module
    net: torch.nn.Module
    optim: torch.optim.Optimizer
    scaler: Any
    sampler: mining.AnchorSampler
    tuple_rng: np.random.Generator
    cache: np.ndarray | None = None
    cache_step: int = -1
    step: int = 0
    refreshes: int = 0
    saved_step: int = 0


def prepare_data(
    cfg: TrainConfig,
    rt: Runtime,
    training_set: TrainingSet | None = None,
    val_runs: list[EvalRun] | None = None,
    progress: bool = True,
) -> TrainData:
    """Load the training set (unless given) and check it can feed the configured steps, then
    read every training cloud into RAM. Raises :class:`InputError` naming the option to change
    when the data is too small for it; nothing is written."""
    import torch

    t = cfg.train
    d = rt.dist
    if training_set is None:
        from pnvlad_service.data.dataset import load_training_data

        training_set, loaded_val = load_training_data(cfg.data)
        val_runs = val_runs if val_runs is not None else loaded_val
    min_pos = min(2, t.positives)
    unweighted = training_set.anchors(min_positives=min_pos)
    anchors = mining.weighted_anchors(training_set, unweighted, cfg.data.dataset_weights, t.seed)
    if len(anchors) < t.batch_size:
        raise InputError(
            f"only {len(anchors)} anchors with at least {min_pos} positives, fewer than the "
            f"batch size {t.batch_size}: lower --batch-size or use a larger tree",
            source="training set",
        )
    if t.batch_size % d.world:
        raise InputError(
            f"batch size {t.batch_size} is not a multiple of the {d.world} processes",
            source="train.batch_size",
        )
    negatives, hard = t.negatives, t.hard_negatives
    if t.mining == "tuple":
        negatives, hard = mining.fit_negatives(training_set, anchors, negatives, hard)
    val_runs = list(val_runs or [])
    if t.val_every and len(val_runs) == 1:
        log.warning("no validation: the evaluation set has a single run (recall needs two)")
        val_runs = []
    if d.main:
        log.info(
            "training set: %d submaps, %d anchors (%d skipped with < 2 positives), %d an epoch",
            len(training_set),
            len(unweighted),
            len(training_set) - len(unweighted),
            len(anchors),
        )
    # Resampling holds the submaps whole (at least num_points: fit_points repeats rows of a
    # smaller one) and draws the subset in the step (train._embed).
    held = max(SUBMAP_POINTS, cfg.model.num_points) if t.resample_points else cfg.model.num_points
    clouds_np = load_clouds(
        training_set.paths,
        held,
        workers=t.workers,
        progress=progress and d.main,
        point_features=shape_feature_fn(cfg.model.local_k),
    )
    clouds = torch.from_numpy(clouds_np)
    if rt.device.type == "cuda":
        clouds = clouds.pin_memory()
    return TrainData(training_set, anchors, clouds, val_runs, negatives, hard)


def build_state(
    cfg: TrainConfig,
    rt: Runtime,
    data: TrainData,
    on_model: Callable[[torch.nn.Module], None] | None = None,
    init: dict[str, Any] | None = None,
) -> TrainState:
    """A fresh model (seeded with ``train.seed``; ``init``: with those weights, as
    :func:`~pnvlad_service.training.init.initial_weights` read them), Adam, the grad scaler
    (fp16 only), the anchor sampler and the tuple RNG, all as at step 0."""
    import torch

    from pnvlad_service.models.factory import build_model

    t = cfg.train
    torch.manual_seed(t.seed)
    model = build_model(cfg.model)
    if init is not None:
        model.load_state_dict(init, strict=True)
    model = model.to(rt.device)
    if on_model is not None:
        on_model(model)
    return TrainState(
        model=model,
        net=model,
        optim=torch.optim.Adam(model.parameters(), lr=t.lr, weight_decay=t.weight_decay),
        scaler=torch.amp.GradScaler("cuda", enabled=rt.amp_dtype == torch.float16),
        sampler=mining.AnchorSampler(data.anchors, t.seed),
        tuple_rng=np.random.default_rng([t.seed, 1]),
    )


# ---------------------------------------------------------------------------------------------
# resume and checkpoints


def checkpoint_to_resume(out: Path, resume: bool) -> Path | None:
    """The checkpoint ``resume`` continues from (None for a fresh run); refuses a fresh run in
    a directory that holds one, and ``resume`` without one."""
    ckpt = latest_checkpoint(out)
    if resume and ckpt is None:
        raise InputError("--resume: no checkpoint under this output directory", source=out)
    if not resume and ckpt is not None:
        raise InputError(
            "output directory already holds a training run (use --resume, or another --out)",
            source=out,
        )
    return ckpt


def resume_state(state: TrainState, ckpt: Path) -> None:
    """Put ``state`` where checkpoint ``ckpt`` left it: weights, optimiser, scaler, torch RNGs,
    cache, step counters, anchor order and tuple RNG."""
    weights, saved, _ = load_checkpoint(ckpt)
    state.model.load_state_dict(weights)
    state.optim.load_state_dict(saved.tensors["optimizer"])
    if "scaler" in saved.tensors:
        state.scaler.load_state_dict(saved.tensors["scaler"])
    restore_rng_state(saved.tensors["rng"])
    if "cache" in saved.tensors:
        state.cache = saved.tensors["cache"].numpy()
    info = saved.info
    state.step = state.saved_step = int(info["step"])
    state.cache_step = int(info["cache_step"])
    state.refreshes = int(info.get("cache_refreshes", 0))
    state.sampler.load_state(info["sampler"])
    state.tuple_rng.bit_generator.state = info["tuple_rng"]


def save_state(state: TrainState, cfg: TrainConfig, out: Path, elapsed_s: float) -> None:
    """Write the checkpoint of ``state.step`` under ``out`` (call on rank 0 only)."""
    import torch

    tensors: dict[str, Any] = {
        "optimizer": state.optim.state_dict(),
        "scaler": state.scaler.state_dict(),
        "rng": rng_state_tensors(),
    }
    if state.cache is not None:
        tensors["cache"] = torch.from_numpy(state.cache)
    info = {
        "epoch": state.sampler.epoch,
        "cache_step": state.cache_step,
        "cache_refreshes": state.refreshes,
        "sampler": state.sampler.state(),
        "tuple_rng": state.tuple_rng.bit_generator.state,
        "config": cfg.model_dump(mode="json"),
        "elapsed_s": round(elapsed_s, 3),
    }
    keep = cfg.train.keep_checkpoints
    save_checkpoint(
        out, state.step, state.model, cfg.model, TrainingState(tensors, info), keep=keep
    )
    state.saved_step = state.step
