"""Training the encoder: one process, or several with ``torchrun`` (DistributedDataParallel).

A step (tuple mode, the paper): ``batch_size`` anchors from a shuffled epoch order, each with
P positives, Nn negatives (hard ones from a descriptor cache once it exists) and one other
negative; the distinct clouds of the step go through the network once, in one forward pass, and
the loss (lazy quadruplet by default) is computed on the gathered embeddings. In-batch mode
(``train.mining: in_batch``): the step is the anchors plus one positive each, and every pair of
the batch that the training set labels positive or negative is a candidate, so each embedding
serves every tuple it can.

Schedules follow the published TensorFlow code: learning rate ``lr * rate^floor(tuples seen /
decay_samples)`` floored at ``lr_min``; batch-norm decay ``min(clip, 1 - init * rate^floor(...))``
(PyTorch momentum = 1 - decay).

Distributed: every rank draws the same global batch (same seed) and takes its share of the
anchors; the descriptor cache is computed in shards and all-gathered; only rank 0 writes
checkpoints, the metrics log and the final model. ``gloo`` on CPU, ``nccl`` on CUDA.

The run is in named steps: ``runtime.setup_runtime`` (device, AMP, process group),
``state.prepare_data`` (the data, checked against the config before anything is written),
``state.build_state`` / ``state.resume_state``, then a loop of :func:`tuple_step` or
:func:`in_batch_step` with cache refreshes, validation and ``state.save_state`` on schedule.

Outputs under ``OUT``: ``checkpoints/`` (see ``checkpoint.py``), ``metrics.jsonl`` (one JSON
object a line: ``event`` = ``step`` | ``cache`` | ``val`` | ``start`` | ``end``), ``model/``
(the final weights), ``config.yaml`` (the resolved config).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun, TrainingSet
from pnvlad_service.fileio import atomic_write_text
from pnvlad_service.models.embedding import embed_in_chunks, module_embedder
from pnvlad_service.training import mining
from pnvlad_service.training.augment import augment
from pnvlad_service.training.config import TrainConfig
from pnvlad_service.training.init import initial_weights
from pnvlad_service.training.runtime import (
    Runtime,
    any_rank,
    gather_rows,
    mean_over_ranks,
    setup_runtime,
    shutdown,
    wrap_ddp,
)
from pnvlad_service.training.state import (
    TrainData,
    TrainState,
    build_state,
    checkpoint_to_resume,
    prepare_data,
    resume_state,
    save_state,
)

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a run did: ``steps`` done in total (including before a resume), ``losses`` of the
    steps of this invocation (step -> loss), the final model directory (rank 0) and why it
    stopped (``"done"`` | ``"max_steps"`` | ``"max_minutes"``)."""

    steps: int
    losses: dict[int, float] = field(default_factory=dict)
    model_dir: Path | None = None
    stopped: str = "done"
    seconds: float = 0.0
    cache_refreshes: int = 0
    last_val: dict[str, Any] | None = None

    def summary(self) -> str:
        """One line: steps, why it stopped, seconds, the last loss and the model directory."""
        last = self.losses[max(self.losses)] if self.losses else float("nan")
        return (
            f"{self.steps} steps ({self.stopped}) in {self.seconds:.0f} s, last loss {last:.4f}; "
            f"model: {self.model_dir}"
        )


# ---------------------------------------------------------------------------------------------
# schedules


def learning_rate(cfg: TrainConfig, step: int, total_steps: int | None = None) -> float:
    """Learning rate before step ``step`` (0-based): the staircase decay on tuples seen, or
    (``lr_schedule: cosine``) a half cosine from ``lr`` to ``lr_min`` over ``total_steps``
    (the run's epochs), after ``warmup_steps`` of linear climb in either case."""
    t = cfg.train
    if step < t.warmup_steps:
        return t.lr * (step + 1) / t.warmup_steps
    if t.lr_schedule == "cosine":
        if total_steps is None:
            raise ValueError("the cosine schedule needs the run's total steps")
        span = max(total_steps - t.warmup_steps, 1)
        done = min((step - t.warmup_steps) / span, 1.0)
        return t.lr_min + (t.lr - t.lr_min) * 0.5 * (1.0 + math.cos(math.pi * done))
    seen = step * t.batch_size
    return max(t.lr * t.lr_decay_rate ** (seen // t.lr_decay_samples), t.lr_min)


def bn_momentum(cfg: TrainConfig, step: int) -> float:
    """PyTorch batch-norm momentum before step ``step``: 1 - the TF code's decay."""
    t = cfg.train
    seen = step * t.batch_size
    decay = min(
        t.bn_decay_clip, 1 - t.bn_init_decay * t.bn_decay_rate ** (seen // t.bn_decay_samples)
    )
    return 1.0 - decay


# ---------------------------------------------------------------------------------------------
# losses


def make_loss(cfg: TrainConfig) -> Callable[..., torch.Tensor]:
    """``loss(query [B,D], positives [B,P,D], negatives [B,Nn,D], other [B,D]) -> scalar``."""
    from pnvlad_service.training import losses

    t = cfg.train
    fn = losses.get_loss(t.loss)

    def loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, o: torch.Tensor) -> torch.Tensor:
        if "quadruplet" in t.loss:
            return fn(q, p, n, o, margin=t.margin1, second_margin=t.margin2)
        return fn(q, p, n, o, margin=t.margin1)

    return loss


# ---------------------------------------------------------------------------------------------
# descriptors

#: Clouds gathered from RAM at a time for the cache (a multiple of the embedding batch, so the
#: batches the network sees are those of one pass over all the indices).
CACHE_CHUNK = 1024


def compute_cache(
    model: torch.nn.Module, clouds: torch.Tensor, rt: Runtime, batch: int = 64
) -> np.ndarray:
    """float32 [N, D] descriptors of every training cloud (``clouds`` float32 [N, P, 3]) with
    ``model`` in eval mode; with several ranks each embeds the indices ``rank::world`` and the
    shards are all-gathered."""
    import torch

    n = clouds.shape[0]
    mine = np.arange(rt.dist.rank, n, rt.dist.world, dtype=np.int64)
    embed = module_embedder(model, rt.device, batch=batch, amp_dtype=rt.amp_dtype)
    desc = embed_in_chunks(
        embed, len(mine), lambda s, e: clouds[torch.from_numpy(mine[s:e])], chunk=CACHE_CHUNK
    )
    return gather_rows(desc, n, rt)


# ---------------------------------------------------------------------------------------------
# one step

#: A step's forward: (loss, distinct clouds embedded, the step's indices for ``on_step``).
StepOut = tuple["torch.Tensor", int, np.ndarray]


def _embed(
    state: TrainState,
    clouds: torch.Tensor,
    idx: np.ndarray,
    rt: Runtime,
    cfg: TrainConfig,
    quarter: bool = False,
) -> torch.Tensor:
    """float32 [len(idx), D]: one forward pass (training mode, autocast) over ``clouds[idx]``,
    each cloud cut to ``model.num_points`` when it is held whole (``train.resample_points``) and
    augmented when the config asks (the seeds drawn from the tuple RNG, so a resumed run
    repeats the subsets and the augmentation); ``quarter``: each also turned by a random
    quarter turn (the turned negatives' copies)."""
    import torch

    net = state.net
    x = clouds[torch.from_numpy(idx)].to(rt.device, non_blocking=True)
    n = cfg.model.num_points
    if x.shape[1] > n:  # train.resample_points: a fresh subset of each whole submap
        g = torch.Generator(device=x.device)
        g.manual_seed(int(state.tuple_rng.integers(0, 2**62)))
        keep = torch.rand(x.shape[:2], generator=g, device=x.device).argsort(dim=1)[:, :n]
        x = x.gather(1, keep.sort(dim=1).values.unsqueeze(-1).expand(-1, -1, x.shape[2]))
    if cfg.train.augment.active:
        seed = int(state.tuple_rng.integers(0, 2**62))
        x = augment(x, cfg.train.augment, seed)
    if quarter:  # each cloud a random 1, 2 or 3 quarter turns (train.turned_negatives)
        k = torch.from_numpy(state.tuple_rng.integers(1, 4, len(idx))).to(x.device)
        c = torch.cos(k * (math.pi / 2)).round().to(x.dtype)[:, None]
        s = torch.sin(k * (math.pi / 2)).round().to(x.dtype)[:, None]
        xy = torch.stack([c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1]], -1)
        x = torch.cat([xy, x[..., 2:]], dim=-1)
    with torch.autocast(rt.device.type, dtype=rt.amp_dtype, enabled=rt.amp_dtype is not None):
        emb = net(x)
    return emb.float()


def tuple_step(
    state: TrainState,
    data: TrainData,
    rt: Runtime,
    cfg: TrainConfig,
    loss_fn: Callable[..., torch.Tensor],
    batch_anchors: np.ndarray,
) -> StepOut:
    """The paper's step: a tuple per anchor of the global batch (hard negatives from the cache
    once it exists), this rank's share of them, every distinct cloud embedded once; the
    indices are this rank's tuples int64 [b, 1 + P + Nn + 1]."""
    import torch

    t = cfg.train
    hard = data.hard_negatives
    tb = mining.sample_tuples(
        state.tuple_rng,
        data.training_set,
        batch_anchors,
        positives=t.positives,
        negatives=data.negatives,
        cache=state.cache if hard > 0 else None,
        hard=hard,
        sampled=t.sampled_negatives,
    )
    table = tb.table()[rt.dist.rank :: rt.dist.world]
    uniq, inv = np.unique(table, return_inverse=True)
    emb = _embed(state, data.clouds, uniq, rt, cfg)
    e = emb[torch.from_numpy(inv.reshape(table.shape)).to(rt.device)]  # [b, 1 + P + Nn + 1, D]
    q, p = e[:, 0], e[:, 1 : 1 + t.positives]
    n, o = e[:, 1 + t.positives : -1], e[:, -1]
    return loss_fn(q, p, n, o), len(uniq), table


def in_batch_step(
    state: TrainState,
    data: TrainData,
    rt: Runtime,
    cfg: TrainConfig,
    loss_fn: Callable[..., torch.Tensor],
    batch_anchors: np.ndarray,
) -> StepOut:
    """In-batch mining: this rank's anchors plus a positive each are embedded once, and every
    member with a positive and a negative in the batch gets a tuple from the batch's
    descriptors (a zero loss when none has); the indices are the members int64 [M]."""
    import torch

    members = mining.in_batch_members(
        state.tuple_rng, data.training_set, batch_anchors[rt.dist.rank :: rt.dist.world]
    )
    emb = _embed(state, data.clouds, members, rt, cfg)
    pos_m, neg_m = mining.pair_masks(data.training_set, members)
    if cfg.train.turned_negatives:
        turned = _embed(state, data.clouds, members, rt, cfg, quarter=True)
        emb = torch.cat([emb, turned])
        pos_m, neg_m = mining.with_turned_copies(pos_m, neg_m)
    tb = mining.in_batch_tuples(emb.detach().cpu().numpy(), pos_m, neg_m, data.negatives)
    if tb is None:
        return emb.sum() * 0.0, len(members), members
    e = emb[torch.from_numpy(tb.table()).to(rt.device)]
    return loss_fn(e[:, 0], e[:, 1:2], e[:, 2:-1], e[:, -1]), len(members), members


def _refresh_cache_if_due(
    state: TrainState, cfg: TrainConfig, data: TrainData, rt: Runtime, mlog: _Log
) -> None:
    """Recompute the hard-negative cache on schedule (tuple mode with hard negatives only)."""
    t = cfg.train
    if t.mining != "tuple" or data.hard_negatives == 0:
        return
    if state.sampler.epoch < t.cache_warmup_epochs:
        return
    if state.cache is not None and state.step - state.cache_step < t.cache_refresh_steps:
        return
    tc = time.monotonic()
    state.cache = compute_cache(state.model, data.clouds, rt)
    state.cache_step = state.step
    state.refreshes += 1
    mlog.write(event="cache", step=state.step, seconds=round(time.monotonic() - tc, 3))


def _apply_schedules(state: TrainState, cfg: TrainConfig, total_steps: int) -> tuple[float, float]:
    """Set this step's learning rate and batch-norm momentum; returns both."""
    import torch

    lr = learning_rate(cfg, state.step, total_steps)
    mom = bn_momentum(cfg, state.step)
    for g in state.optim.param_groups:
        g["lr"] = lr
    for m in state.model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.momentum = mom
    return lr, mom


def _optimise(state: TrainState, loss: torch.Tensor) -> None:
    state.optim.zero_grad(set_to_none=True)
    state.scaler.scale(loss).backward()
    state.scaler.step(state.optim)
    state.scaler.update()


# ---------------------------------------------------------------------------------------------
# the run


class _Log:
    """metrics.jsonl writer (rank 0 only); one JSON object a line, flushed each line."""

    def __init__(self, path: Path | None) -> None:
        self.fh = open(path, "a", encoding="utf-8") if path is not None else None  # noqa: SIM115

    def write(self, **rec: Any) -> None:
        if self.fh is not None:
            rec["time"] = round(time.time(), 3)
            self.fh.write(json.dumps(rec) + "\n")
            self.fh.flush()

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()


@dataclass
class _Loop:
    """What the step loop needs besides the state: the run's fixed parts and its hooks."""

    cfg: TrainConfig
    out: Path
    rt: Runtime
    data: TrainData
    mlog: _Log
    result: TrainResult
    total: int
    t0: float
    progress: bool
    on_step: Callable[[dict[str, Any]], None] | None
    full: int = 0  # the steps of the configured epochs (the cosine schedule's span)


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    training_set: TrainingSet | None = None,
    val_runs: list[EvalRun] | None = None,
    resume: bool = False,
    progress: bool = True,
    on_model: Callable[[torch.nn.Module], None] | None = None,
    on_step: Callable[[dict[str, Any]], None] | None = None,
) -> TrainResult:
    """Train ``cfg.model`` on ``training_set`` (or the tree and splits named in ``cfg.data``)
    and write checkpoints, ``metrics.jsonl`` and the final model under ``out``.

    ``resume`` continues from the newest checkpoint under ``out`` (same step, optimiser, RNGs
    and descriptor cache, so the next step's loss equals the uninterrupted run's). ``on_model``
    sees the (unwrapped) model once built, ``on_step`` each step's record: hooks for tests and
    tools. Under ``torchrun`` (``WORLD_SIZE`` > 1) each process calls this with the same config.
    """
    t0 = time.monotonic()
    out = Path(out)
    t = cfg.train
    ckpt = checkpoint_to_resume(out, resume)
    # A resumed run takes its weights from its checkpoint; a fresh one from train.init, if any.
    init = initial_weights(cfg.model, t.init) if ckpt is None and t.init is not None else None
    rt = setup_runtime(t)
    data = prepare_data(cfg, rt, training_set, val_runs, progress)
    state = build_state(cfg, rt, data, on_model, init=init)
    if ckpt is not None:
        resume_state(state, ckpt)
        if rt.dist.main:
            log.info("resumed from %s at step %d", ckpt, state.step)
    state.net = wrap_ddp(state.model, rt)
    state.model.train()
    full = t.epochs * state.sampler.steps_per_epoch(t.batch_size)
    total = full if t.max_steps is None else min(full, t.max_steps)
    mlog = _start_log(cfg, out, rt, data, state, total, resumed=ckpt is not None)
    loop = _Loop(
        cfg, out, rt, data, mlog, TrainResult(steps=state.step), total, t0, progress, on_step, full
    )
    try:
        stopped = _run_steps(loop, state)
        if state.step >= total and t.max_steps is not None and total == t.max_steps:
            stopped = "max_steps" if total < full else "done"
        loop.result.model_dir = _finish(loop, state, stopped)
    finally:
        mlog.close()
        shutdown(rt)
    res = loop.result
    res.steps, res.stopped, res.cache_refreshes = state.step, stopped, state.refreshes
    res.seconds = time.monotonic() - t0
    if rt.dist.main:
        log.info("trained %d steps in %.1f s (%s)", state.step, res.seconds, stopped)
    return res


def _start_log(
    cfg: TrainConfig,
    out: Path,
    rt: Runtime,
    data: TrainData,
    state: TrainState,
    total: int,
    resumed: bool,
) -> _Log:
    """Create ``out`` with ``config.yaml`` and open ``metrics.jsonl`` with its ``start`` line
    (rank 0; the other ranks get a log that writes nothing)."""
    if not rt.dist.main:
        return _Log(None)
    out.mkdir(parents=True, exist_ok=True)
    mlog = _Log(out / "metrics.jsonl")
    atomic_write_text(out / "config.yaml", cfg.to_yaml())
    mlog.write(
        event="start",
        step=state.step,
        total=total,
        resumed=resumed,
        world=rt.dist.world,
        device=str(rt.device),
        anchors=len(data.anchors),
        submaps=len(data.training_set),
    )
    return mlog


def _run_steps(loop: _Loop, state: TrainState) -> str:
    """Steps until ``loop.total`` (``"done"``) or the time budget is spent (``"max_minutes"``,
    every rank at the same step), with cache refreshes, logging, validation and checkpoints on
    schedule."""
    from pnvlad_service.progress import tqdm

    cfg, rt, t = loop.cfg, loop.rt, loop.cfg.train
    loss_fn = make_loss(cfg)
    step_fn = tuple_step if t.mining == "tuple" else in_batch_step
    bar = tqdm(
        total=loop.total,
        initial=state.step,
        desc="train",
        unit="step",
        disable=not (loop.progress and rt.dist.main),
    )
    first_step, t_loop = state.step, time.monotonic()
    try:
        while state.step < loop.total:
            spent = time.monotonic() - loop.t0
            if t.max_minutes is not None and any_rank(spent > 60 * t.max_minutes, rt):
                return "max_minutes"
            _refresh_cache_if_due(state, cfg, loop.data, rt, loop.mlog)
            lr, mom = _apply_schedules(state, cfg, loop.full)
            batch_anchors = state.sampler.next(t.batch_size)
            loss, clouds, indices = step_fn(state, loop.data, rt, cfg, loss_fn, batch_anchors)
            _optimise(state, loss)
            state.step += 1
            lv = mean_over_ranks(float(loss.detach()), rt)
            loop.result.losses[state.step] = lv
            rec = {
                "event": "step",
                "step": state.step,
                "epoch": state.sampler.epoch,
                "loss": lv,
                "lr": lr,
                "bn_momentum": mom,
                "clouds": clouds,
            }
            if loop.on_step is not None:
                loop.on_step({**rec, "indices": indices})
            if state.step % t.log_every == 0 or state.step == loop.total:
                rec["steps_per_s"] = round(
                    (state.step - first_step) / (time.monotonic() - t_loop), 4
                )
                loop.mlog.write(**rec)
            bar.set_postfix(loss=f"{lv:.4f}", epoch=state.sampler.epoch)
            bar.update()
            _after_step(loop, state)
    finally:
        bar.close()
    return "done"


def _after_step(loop: _Loop, state: TrainState) -> None:
    """Validation and checkpoint when their schedules say so."""
    t, rt = loop.cfg.train, loop.rt
    if t.val_every and state.step % t.val_every == 0 and loop.data.val_runs and rt.dist.main:
        loop.result.last_val = _validate(
            state.model, loop.cfg, loop.data.val_runs, rt.device, loop.mlog, state.step
        )
    if state.step % t.checkpoint_every == 0:
        if rt.dist.main:
            save_state(state, loop.cfg, loop.out, time.monotonic() - loop.t0)
        state.saved_step = state.step


def _finish(loop: _Loop, state: TrainState, stopped: str) -> Path | None:
    """The last checkpoint (unless just written), the final model (rank 0: its directory) and
    the ``end`` line."""
    main = loop.rt.dist.main
    if state.step != state.saved_step and main:
        save_state(state, loop.cfg, loop.out, time.monotonic() - loop.t0)
    model_dir = None
    if main:
        from pnvlad_service.models.store import save_model

        meta = {"source": "pnvlad train", "step": state.step, "stopped": stopped}
        model_dir = save_model(
            loop.out / "model", state.model, loop.cfg.model, meta, overwrite=True
        )
    seconds = round(time.monotonic() - loop.t0, 3)
    loop.mlog.write(event="end", step=state.step, stopped=stopped, seconds=seconds)
    if main:
        _write_curve(loop.out)
    return model_dir


def _write_curve(out: Path) -> None:
    """``OUT/learning_curve.png`` from the run's log, when matplotlib (the plot extra) is
    installed; a training run never fails for want of it."""
    from pnvlad_service.errors import MissingDependencyError
    from pnvlad_service.training.curves import read_curve, write_learning_curves

    try:
        write_learning_curves([read_curve(out)], out / "learning_curve.png", title=out.name)
    except MissingDependencyError:
        log.info("no learning_curve.png: matplotlib is not installed (pip install 'pnvlad[plot]')")


def _validate(
    model: torch.nn.Module,
    cfg: TrainConfig,
    runs: list[EvalRun],
    device: torch.device,
    mlog: _Log,
    step: int,
) -> dict[str, Any]:
    """Recall of the current weights on (up to ``data.val_max_runs``) evaluation runs."""
    from pnvlad_service.evaluation.evaluate import evaluate_runs

    runs = runs[: cfg.data.val_max_runs]
    tv = time.monotonic()
    rep = evaluate_runs(
        module_embedder(model, device),
        runs,
        cfg.model.num_points,
        progress=False,
        shape_k=cfg.model.local_k,
    )
    rec = {
        "event": "val",
        "step": step,
        "recall_at_1": rep["recall_at_1"],
        "recall_at_1pct": rep["recall_at_1pct"],
        "seconds": round(time.monotonic() - tv, 3),
    }
    mlog.write(**rec)
    log.info(
        "step %d: validation recall@1 %.2f, recall@1%% %.2f",
        step,
        rec["recall_at_1"],
        rec["recall_at_1pct"],
    )
    return rec
