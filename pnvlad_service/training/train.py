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

Outputs under ``OUT``: ``checkpoints/`` (see ``checkpoint.py``), ``metrics.jsonl`` (one JSON
object a line: ``event`` = ``step`` | ``cache`` | ``val`` | ``start`` | ``end``), ``model/``
(the final weights), ``config.yaml`` (the resolved config).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun, TrainingSet, load_clouds
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text
from pnvlad_service.training import mining
from pnvlad_service.training.checkpoint import (
    TrainingState,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from pnvlad_service.training.config import TrainConfig

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


# ---------------------------------------------------------------------------------------------
# schedules


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Learning rate before step ``step`` (0-based): staircase decay on tuples seen."""
    t = cfg.train
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
# distributed helpers


@dataclass
class Dist:
    """Process group facts: ``rank``, ``world`` size, ``local_rank``; ``world == 1`` alone."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def _init_dist(device_kind: str) -> Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device_kind == "cuda" else "gloo")
    return Dist(
        rank=dist.get_rank(),
        world=dist.get_world_size(),
        local_rank=int(os.environ.get("LOCAL_RANK", "0")),
        local_world=int(os.environ.get("LOCAL_WORLD_SIZE", str(world))),
    )


def _pick_device(name: str, d: Dist) -> torch.device:
    import torch

    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise InputError("CUDA requested but not available", source="train.device")
        if name == "cuda":
            name = f"cuda:{d.local_rank}"
        torch.cuda.set_device(torch.device(name))
    return torch.device(name)


def _any_rank(flag: bool, d: Dist, device: torch.device) -> bool:
    """True on every rank when ``flag`` is true on any (one all-reduce; plain value alone)."""
    if d.world == 1:
        return flag
    import torch
    import torch.distributed as dist

    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def _cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


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


def embed_all(
    model: torch.nn.Module,
    clouds: torch.Tensor,
    indices: np.ndarray,
    device: torch.device,
    batch: int = 64,
    amp_dtype: Any = None,
) -> np.ndarray:
    """float32 [len(indices), D] descriptors of ``clouds[indices]`` with ``model`` in eval mode
    (the mode is restored afterwards)."""
    import torch

    was = model.training
    model.eval()
    out = []
    with torch.inference_mode():
        for s in range(0, len(indices), batch):
            x = clouds[torch.from_numpy(indices[s : s + batch])].to(device, non_blocking=True)
            with torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None):
                out.append(model(x).float().cpu().numpy())
    model.train(was)
    if not out:
        return np.zeros((0, 0), dtype=np.float32)
    return np.concatenate(out).astype(np.float32)


def compute_cache(
    model: torch.nn.Module,
    clouds: torch.Tensor,
    device: torch.device,
    d: Dist,
    amp_dtype: Any = None,
    batch: int = 64,
) -> np.ndarray:
    """float32 [N, D] descriptors of every training cloud; with several ranks each embeds the
    indices ``rank::world`` and the shards are all-gathered."""
    import torch

    n = clouds.shape[0]
    mine = np.arange(d.rank, n, d.world, dtype=np.int64)
    desc = embed_all(model, clouds, mine, device, batch, amp_dtype)
    if d.world == 1:
        return desc
    import torch.distributed as dist

    rows = math.ceil(n / d.world)
    dim = desc.shape[1]
    buf = torch.zeros(rows, dim, dtype=torch.float32, device=device)
    buf[: len(desc)] = torch.from_numpy(desc).to(device)
    parts = [torch.zeros_like(buf) for _ in range(d.world)]
    dist.all_gather(parts, buf)
    full = np.zeros((n, dim), dtype=np.float32)
    for r, part in enumerate(parts):
        idx = np.arange(r, n, d.world)
        full[idx] = part[: len(idx)].cpu().numpy()
    return full


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


def _rng_state_tensors() -> dict[str, Any]:
    import torch

    out: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


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
    import torch

    t0 = time.monotonic()
    out = Path(out)
    t = cfg.train
    dev_kind = (
        "cuda"
        if (t.device.startswith("cuda") or (t.device == "auto" and torch.cuda.is_available()))
        else "cpu"
    )
    d = _init_dist(dev_kind)
    device = _pick_device(t.device, d)
    if device.type == "cpu":
        torch.set_num_threads(t.threads or max(1, _cpu_count() // d.local_world))
    amp_dtype = None
    if device.type == "cuda" and t.amp != "off":
        bf16 = t.amp == "bf16" or (t.amp == "auto" and torch.cuda.is_bf16_supported())
        amp_dtype = torch.bfloat16 if bf16 else torch.float16

    ckpt = latest_checkpoint(out) if resume else None
    if resume and ckpt is None:
        raise InputError("--resume: no checkpoint under this output directory", source=out)
    if not resume and latest_checkpoint(out) is not None:
        raise InputError(
            "output directory already holds a training run (use --resume, or another --out)",
            source=out,
        )

    if training_set is None:
        from pnvlad_service.data.dataset import load_training_data

        training_set, loaded_val = load_training_data(cfg.data)
        val_runs = val_runs if val_runs is not None else loaded_val
    anchors = training_set.anchors(min_positives=min(2, t.positives))
    skipped = len(training_set) - len(anchors)
    if len(anchors) < t.batch_size:
        raise InputError(
            f"only {len(anchors)} anchors with at least 2 positives, fewer than the batch size "
            f"{t.batch_size}",
            source="training set",
        )
    if t.batch_size % d.world:
        raise InputError(
            f"batch size {t.batch_size} is not a multiple of the {d.world} processes",
            source="train.batch_size",
        )
    if d.main:
        log.info(
            "training set: %d submaps, %d anchors (%d skipped with < 2 positives)",
            len(training_set),
            len(anchors),
            skipped,
        )
    clouds_np = load_clouds(
        training_set.paths, cfg.model.num_points, workers=t.workers, progress=progress and d.main
    )
    clouds = torch.from_numpy(clouds_np)
    if device.type == "cuda":
        clouds = clouds.pin_memory()

    from pnvlad_service.models.pointnetvlad import build_model

    torch.manual_seed(t.seed)
    model = build_model(cfg.model).to(device)
    if on_model is not None:
        on_model(model)
    optim = torch.optim.Adam(model.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    scaler = torch.amp.GradScaler("cuda", enabled=amp_dtype == torch.float16)
    sampler = mining.AnchorSampler(anchors, t.seed)
    tuple_rng = np.random.default_rng([t.seed, 1])
    cache: np.ndarray | None = None
    cache_step = -1
    step = 0
    refreshes = 0

    if ckpt is not None:
        weights, state, _ = load_checkpoint(ckpt)
        model.load_state_dict(weights)
        optim.load_state_dict(state.tensors["optimizer"])
        if "scaler" in state.tensors:
            scaler.load_state_dict(state.tensors["scaler"])
        torch.set_rng_state(state.tensors["rng"]["torch"])
        if "cuda" in state.tensors["rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state.tensors["rng"]["cuda"])
        if "cache" in state.tensors:
            cache = state.tensors["cache"].numpy()
        info = state.info
        step = int(info["step"])
        cache_step = int(info["cache_step"])
        refreshes = int(info.get("cache_refreshes", 0))
        sampler.load_state(info["sampler"])
        tuple_rng.bit_generator.state = info["tuple_rng"]
        if d.main:
            log.info("resumed from %s at step %d", ckpt, step)

    net: torch.nn.Module = model
    if d.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    model.train()
    loss_fn = make_loss(cfg)
    steps_per_epoch = sampler.steps_per_epoch(t.batch_size)
    total = t.epochs * steps_per_epoch
    if t.max_steps is not None:
        total = min(total, t.max_steps)

    if d.main:
        out.mkdir(parents=True, exist_ok=True)
    mlog = _Log(out / "metrics.jsonl" if d.main else None)
    if d.main:
        atomic_write_text(out / "config.yaml", cfg.to_yaml())
        mlog.write(
            event="start",
            step=step,
            total=total,
            resumed=ckpt is not None,
            world=d.world,
            device=str(device),
            anchors=len(anchors),
            submaps=len(training_set),
        )

    def checkpoint() -> None:
        if not d.main:
            return
        tensors: dict[str, Any] = {
            "optimizer": optim.state_dict(),
            "scaler": scaler.state_dict(),
            "rng": _rng_state_tensors(),
        }
        if cache is not None:
            tensors["cache"] = torch.from_numpy(cache)
        info = {
            "epoch": sampler.epoch,
            "cache_step": cache_step,
            "cache_refreshes": refreshes,
            "sampler": sampler.state(),
            "tuple_rng": tuple_rng.bit_generator.state,
            "config": cfg.model_dump(mode="json"),
            "elapsed_s": round(time.monotonic() - t0, 3),
        }
        save_checkpoint(
            out, step, model, cfg.model, TrainingState(tensors, info), keep=t.keep_checkpoints
        )

    from tqdm import tqdm

    bar = tqdm(
        total=total, initial=step, desc="train", unit="step", disable=not (progress and d.main)
    )
    result = TrainResult(steps=step)
    stopped = "done"
    last_ckpt = step
    first_step, t_loop = step, time.monotonic()
    try:
        while step < total:
            if t.max_minutes is not None and _any_rank(
                time.monotonic() - t0 > 60 * t.max_minutes, d, device
            ):
                stopped = "max_minutes"  # every rank stops at the same step
                break
            # Hard-negative cache, refreshed on schedule (tuple mode only).
            use_hard = t.mining == "tuple" and t.hard_negatives > 0
            if (
                use_hard
                and sampler.epoch >= t.cache_warmup_epochs
                and (cache is None or step - cache_step >= t.cache_refresh_steps)
            ):
                tc = time.monotonic()
                cache = compute_cache(model, clouds, device, d, amp_dtype)
                cache_step = step
                refreshes += 1
                mlog.write(event="cache", step=step, seconds=round(time.monotonic() - tc, 3))
            lr = learning_rate(cfg, step)
            mom = bn_momentum(cfg, step)
            for g in optim.param_groups:
                g["lr"] = lr
            for m in model.modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                    m.momentum = mom

            batch_anchors = sampler.next(t.batch_size)
            share = batch_anchors[d.rank :: d.world]
            if t.mining == "tuple":
                tb = mining.sample_tuples(
                    tuple_rng,
                    training_set,
                    batch_anchors,
                    positives=t.positives,
                    negatives=t.negatives,
                    cache=cache if use_hard else None,
                    hard=t.hard_negatives,
                    sampled=t.sampled_negatives,
                )
                table = tb.table()[d.rank :: d.world]
                uniq, inv = np.unique(table, return_inverse=True)
                inv = inv.reshape(table.shape)
            else:
                members = mining.in_batch_members(tuple_rng, training_set, share)
                uniq = members
                table = members
            x = clouds[torch.from_numpy(uniq)].to(device, non_blocking=True)
            with torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None):
                emb = net(x)
            emb = emb.float()
            if t.mining == "tuple":
                e = emb[torch.from_numpy(inv).to(device)]  # [b, 1 + P + Nn + 1, D]
                q, p = e[:, 0], e[:, 1 : 1 + t.positives]
                n, o = e[:, 1 + t.positives : -1], e[:, -1]
                loss = loss_fn(q, p, n, o)
            else:
                pos_m, neg_m = mining.pair_masks(training_set, members)
                tb2 = mining.in_batch_tuples(emb.detach().cpu().numpy(), pos_m, neg_m, t.negatives)
                if tb2 is None:
                    loss = emb.sum() * 0.0
                else:
                    tab = torch.from_numpy(tb2.table()).to(device)
                    e = emb[tab]
                    loss = loss_fn(e[:, 0], e[:, 1:2], e[:, 2:-1], e[:, -1])
            optim.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
            step += 1
            lv = float(loss.detach())
            if d.world > 1:
                import torch.distributed as dist

                lt = torch.tensor([lv], device=device)
                dist.all_reduce(lt)
                lv = float(lt) / d.world
            result.losses[step] = lv
            rec = {
                "event": "step",
                "step": step,
                "epoch": sampler.epoch,
                "loss": lv,
                "lr": lr,
                "bn_momentum": mom,
                "clouds": len(uniq),
            }
            if on_step is not None:
                on_step({**rec, "indices": table})
            if step % t.log_every == 0 or step == total:
                rec["steps_per_s"] = round((step - first_step) / (time.monotonic() - t_loop), 4)
                mlog.write(**rec)
            bar.set_postfix(loss=f"{lv:.4f}", epoch=sampler.epoch)
            bar.update()
            if t.val_every and step % t.val_every == 0 and val_runs and d.main:
                result.last_val = _validate(model, cfg, val_runs, device, mlog, step)
            if step % t.checkpoint_every == 0:
                checkpoint()
                last_ckpt = step
        if step >= total and t.max_steps is not None and total == t.max_steps:
            stopped = "max_steps" if total < t.epochs * steps_per_epoch else "done"
        if step != last_ckpt:
            checkpoint()
        if d.main:
            from pnvlad_service.models.store import save_model

            meta = {"source": "pnvlad train", "step": step, "stopped": stopped}
            result.model_dir = save_model(out / "model", model, cfg.model, meta, overwrite=True)
        mlog.write(event="end", step=step, stopped=stopped, seconds=round(time.monotonic() - t0, 3))
    finally:
        bar.close()
        mlog.close()
        if d.world > 1:
            import torch.distributed as dist

            dist.barrier()
            dist.destroy_process_group()
    result.steps = step
    result.stopped = stopped
    result.seconds = time.monotonic() - t0
    result.cache_refreshes = refreshes
    if d.main:
        log.info("trained %d steps in %.1f s (%s)", step, result.seconds, stopped)
    return result


def _validate(
    model: torch.nn.Module,
    cfg: TrainConfig,
    runs: list[EvalRun],
    device: torch.device,
    mlog: _Log,
    step: int,
) -> dict[str, Any]:
    """Recall of the current weights on (up to ``data.val_max_runs``) evaluation runs."""
    from pnvlad_service.evaluation.evaluate import evaluate_runs, model_embedder

    runs = runs[: cfg.data.val_max_runs]
    tv = time.monotonic()
    rep = evaluate_runs(model_embedder(model, device), runs, cfg.model.num_points, progress=False)
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
