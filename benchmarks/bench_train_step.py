"""Training-step speed: the PyTorch port's PN_VLAD against ours, on the same clouds, in one run.

A step is forward + backward + an SGD step on the same B clouds (default 12 of 4,096 points:
one query, 2 positives, 8 negatives and an other negative, lazy quadruplet loss). Contenders:

- ``port``: the port's model as it computes (``benchmarks/port_model.py``);
- ``paper-before`` / ``compact-before`` / ``port-cfg-before``: our modules layer by layer
  (``PointNetVLAD.reference_forward``, the implementation before the fast path);
- ``paper`` / ``compact`` / ``port-cfg``: ``PointNetVLAD.forward``, the fast path
  (``models/training_path.py``);
- the products' work of each step (GFLOP, forward and backward, ``FlopCounterMode``) and the
  rate each contender reaches: a fast path does less work, or does its work faster;
- with ``--bf16 on`` (default ``auto``: only where the CPU has native bfloat16) each of ours
  again under ``torch.autocast("cpu", torch.bfloat16)``; with ``--compile`` each of ours again
  after ``torch.compile``.

The contenders run one step each in turn, round after round, so a noisy neighbour slows all of
them alike; each figure is the median over the rounds, and each ratio the median of the
per-round ratios to the port's step in the same round. The first line names the CPU (its model
name, torch's CPU capability, native bfloat16); ``--profile NAME`` ends with torch's profile of
one more step of that contender (its operators by self time, and by input shape).

    python benchmarks/bench_train_step.py --threads 2 --rounds 7
    python benchmarks/bench_train_step.py --only port,paper,paper-before --bf16 on
    python benchmarks/bench_train_step.py --threads 2 --rounds 3 --only port,paper,compact \
        --profile paper
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from entry import run
from port_model import PortPNVLAD

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import bf16_supported
from pnvlad_service.training.losses import lazy_quadruplet_loss

CONFIGS = {"paper": ModelConfig.paper, "compact": ModelConfig.compact, "port-cfg": ModelConfig.port}


def make_step(
    model: torch.nn.Module,
    x: torch.Tensor,
    amp: bool,
    forward: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Callable[[], float]:
    """One training step on ``x`` [B, N, 3]; returns the loss."""
    opt = torch.optim.SGD(model.parameters(), lr=1e-4, momentum=0.9)
    fwd = forward if forward is not None else model
    b = x.shape[0]
    npos, nneg = 2, b - 4

    def step() -> float:
        opt.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            d = fwd(x)
        d = torch.nn.functional.normalize(d.float(), dim=1)
        loss = lazy_quadruplet_loss(
            d[0:1], d[None, 1 : 1 + npos], d[None, 1 + npos : 1 + npos + nneg], d[-1:]
        )
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step


def cpu_name() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else what platform says."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=12, help="clouds a step")
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--bf16", choices=["auto", "on", "off"], default="auto")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile'd models")
    ap.add_argument("--only", help="comma-separated contenders (default: all)")
    ap.add_argument("--profile", metavar="NAME", help="also profile one step of this contender")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    native = bf16_supported()
    bf16 = args.bf16 == "on" or (args.bf16 == "auto" and native)

    torch.manual_seed(0)
    x = torch.rand(args.batch, args.points, 3) * 2 - 1
    steps: dict[str, Callable[[], float]] = {}
    port = PortPNVLAD(args.points)
    steps["port"] = make_step(port.train(), x, False)
    for name, make in CONFIGS.items():
        torch.manual_seed(1)
        before = build_model(make(num_points=args.points)).train()
        before.fast_path = False
        steps[f"{name}-before"] = make_step(before, x, False)
        torch.manual_seed(1)
        after = build_model(make(num_points=args.points)).train()
        steps[name] = make_step(after, x, False)
        if bf16:
            torch.manual_seed(1)
            m = build_model(make(num_points=args.points)).train()
            steps[f"{name}-bf16"] = make_step(m, x, True)
        if args.compile:
            torch.manual_seed(1)
            m = build_model(make(num_points=args.points)).train()
            steps[f"{name}-compiled"] = make_step(m, x, False, torch.compile(m))
    if args.only:
        keep = set(args.only.split(",")) | {"port"}
        steps = {k: v for k, v in steps.items() if k in keep}

    print(
        f"torch {torch.__version__}, {cpu_name()} ({torch.backends.cpu.get_cpu_capability()}), "
        f"{args.threads} threads, {args.batch} clouds x {args.points} points, "
        f"fwd + bwd + SGD; native bf16: {native}; rounds: {args.rounds}"
    )
    for fn in steps.values():  # warm-up (and compilation)
        fn()
    # The matrix-product work of one step (forward and backward: mm, bmm, addmm, convolutions),
    # as torch's FlopCounterMode counts it; element-wise work is not counted.
    from torch.utils.flop_counter import FlopCounterMode

    flops: dict[str, float] = {}
    for k, fn in steps.items():
        if k.endswith("-compiled"):
            continue
        counter = FlopCounterMode(display=False)
        with counter:
            fn()
        flops[k] = counter.get_total_flops()
    times: dict[str, list[float]] = {k: [] for k in steps}
    for r in range(args.rounds):
        for k, fn in steps.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
        print(f"  round {r + 1}: " + " ".join(f"{k} {v[-1]:.2f}s" for k, v in times.items()))
    print(
        f"\n{'contender':18s} {'s/step':>7s} {'clouds/s':>9s} {'vs port':>8s}"
        f" {'GFLOP/step':>11s} {'GFLOP/s':>8s}"
    )
    for k, v in times.items():
        med = statistics.median(v)
        ratio = statistics.median(p / t for p, t in zip(times["port"], v, strict=True))
        gf = flops.get(k, float("nan")) / 1e9
        print(
            f"{k:18s} {med:7.2f} {args.batch / med:9.2f} {ratio:7.2f}x {gf:11.1f} {gf / med:8.1f}"
        )
    for name in CONFIGS:
        if f"{name}-before" in times and name in times:
            gain = statistics.median(
                b / a for b, a in zip(times[f"{name}-before"], times[name], strict=True)
            )
            print(f"{name}: fast path {gain:.2f}x its before")
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            steps[args.profile]()
        print(f"\none step of {args.profile}, profiled (its time is the profiler's too):")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))
        by_shape = prof.key_averages(group_by_input_shape=True)
        print(by_shape.table(sort_by="self_cpu_time_total", row_limit=25))


if __name__ == "__main__":
    run(main)
