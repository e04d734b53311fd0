"""Where a training run executes: device, mixed precision, and the process group under torchrun.

:func:`setup_runtime` reads ``train.device``, ``train.amp`` and ``train.threads`` and the
``torchrun`` environment (``WORLD_SIZE``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``) once, and the
trainer passes the :class:`Runtime` it returns to every step. The collective helpers
(:func:`any_rank`, :func:`mean_over_ranks`, :func:`gather_rows`) are plain values with a single
process, so the trainer reads the same either way. ``gloo`` on CPU, ``nccl`` on CUDA.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError

if TYPE_CHECKING:
    import torch

    from pnvlad_service.training.config import TrainSection

log = logging.getLogger(__name__)


@dataclass
class Dist:
    """Process group facts: ``rank``, ``world`` size, ``local_rank``; ``world == 1`` alone."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1

    @property
    def main(self) -> bool:
        """True on rank 0, the one that writes files."""
        return self.rank == 0


@dataclass
class Runtime:
    """The process group, the device and the autocast dtype (``None``: full float32)."""

    dist: Dist
    device: torch.device
    amp_dtype: Any = None


def setup_runtime(t: TrainSection) -> Runtime:
    """Join the process group (under torchrun), pick the device, set the CPU threads and choose
    the mixed-precision dtype: bf16 or fp16 on CUDA as ``t.amp`` says; on the CPU bf16 only when
    asked for (``amp: bf16``) and the CPU has native bfloat16 (AVX512-BF16 or AMX), else none
    (``auto`` stays float32 on the CPU: docs/TRAINING.md, "Limits and known failures")."""
    import torch

    cuda_wanted = t.device.startswith("cuda") or (t.device == "auto" and torch.cuda.is_available())
    d = init_dist("cuda" if cuda_wanted else "cpu")
    device = pick_device(t.device, d)
    if device.type == "cpu":
        torch.set_num_threads(t.threads or max(1, cpu_count() // d.local_world))
    amp_dtype = None
    if device.type == "cuda" and t.amp != "off":
        bf16 = t.amp == "bf16" or (t.amp == "auto" and torch.cuda.is_bf16_supported())
        amp_dtype = torch.bfloat16 if bf16 else torch.float16
    elif device.type == "cpu" and t.amp == "bf16":
        from pnvlad_service.models.inference import bf16_supported

        if bf16_supported():
            amp_dtype = torch.bfloat16
        else:
            log.warning("train.amp bf16: this CPU has no native bfloat16; training in float32")
    where = f"{device} ({torch.get_num_threads()} threads)" if device.type == "cpu" else str(device)
    precision = f"{amp_dtype} autocast".replace("torch.", "") if amp_dtype else "float32"
    log.info("training on %s in %s (train.amp %s)", where, precision, t.amp)
    return Runtime(d, device, amp_dtype)


def init_dist(device_kind: str) -> Dist:
    """Join the torchrun process group (``nccl`` for ``"cuda"``, else ``gloo``); alone without
    ``WORLD_SIZE`` > 1."""
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


def pick_device(name: str, d: Dist) -> torch.device:
    """``auto`` | ``cpu`` | ``cuda`` (this rank's local GPU) | ``cuda:N``."""
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


def cpu_count() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def wrap_ddp(model: torch.nn.Module, rt: Runtime) -> torch.nn.Module:
    """``model`` itself alone, a ``DistributedDataParallel`` of it with several processes."""
    if rt.dist.world == 1:
        return model
    from torch.nn.parallel import DistributedDataParallel

    ids = [rt.device.index] if rt.device.type == "cuda" else None
    return DistributedDataParallel(model, device_ids=ids)


def any_rank(flag: bool, rt: Runtime) -> bool:
    """True on every rank when ``flag`` is true on any (one all-reduce; plain value alone)."""
    if rt.dist.world == 1:
        return flag
    import torch
    import torch.distributed as dist

    t = torch.tensor([1.0 if flag else 0.0], device=rt.device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def mean_over_ranks(value: float, rt: Runtime) -> float:
    """The mean of ``value`` over the ranks (the value itself alone)."""
    if rt.dist.world == 1:
        return value
    import torch
    import torch.distributed as dist

    t = torch.tensor([value], device=rt.device)
    dist.all_reduce(t)
    return float(t) / rt.dist.world


def gather_rows(mine: np.ndarray, n: int, rt: Runtime) -> np.ndarray:
    """float32 [n, D] from each rank's rows ``rank::world`` (``mine``: float32 [len, D]), on
    every rank (an all-gather of equal-sized padded blocks); ``mine`` itself alone."""
    d = rt.dist
    if d.world == 1:
        return mine
    import torch
    import torch.distributed as dist

    rows = math.ceil(n / d.world)
    dim = mine.shape[1]
    buf = torch.zeros(rows, dim, dtype=torch.float32, device=rt.device)
    buf[: len(mine)] = torch.from_numpy(mine).to(rt.device)
    parts = [torch.zeros_like(buf) for _ in range(d.world)]
    dist.all_gather(parts, buf)
    full = np.zeros((n, dim), dtype=np.float32)
    for r, part in enumerate(parts):
        idx = np.arange(r, n, d.world)
        full[idx] = part[: len(idx)].cpu().numpy()
    return full


def shutdown(rt: Runtime) -> None:
    """Wait for every rank and leave the process group (nothing alone)."""
    if rt.dist.world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


def rng_state_tensors() -> dict[str, Any]:
    """torch's RNG states (CPU, and every CUDA device when present) for a checkpoint."""
    import torch

    out: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def restore_rng_state(state: dict[str, Any]) -> None:
    """Set torch's RNG states from :func:`rng_state_tensors`' dict."""
    import torch

    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
