"""Learning curves of training runs: loss and validation recall against wall-clock time, read
from each run's ``metrics.jsonl`` (``train.py`` writes it; one JSON object a line).

``pnvlad train`` writes ``OUT/learning_curve.png`` at the end of a run when the ``plot`` extra
is installed; ``benchmarks/plot_runs.py`` puts several runs on one figure (the recipe table of
docs/TRAINING.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError


@dataclass(frozen=True)
class Curve:
    """One run's log: ``minutes`` since its first start (float [S]) of each logged step and
    its ``loss``; the validations' ``val_minutes``, ``recall_at_1`` and ``recall_at_1pct``."""

    name: str
    minutes: np.ndarray
    loss: np.ndarray
    val_minutes: np.ndarray
    recall_at_1: np.ndarray
    recall_at_1pct: np.ndarray


def read_curve(run: str | Path, name: str | None = None) -> Curve:
    """The curve of a run folder (or its ``metrics.jsonl``). A line cut short by a crash is
    skipped; a log without a ``start`` line or any step is refused, naming the file."""
    path = Path(run)
    if path.is_dir():
        path = path / "metrics.jsonl"
    if not path.is_file():
        raise InputError("no metrics.jsonl (is this a pnvlad train run folder?)", path)
    t0 = None
    steps: list[tuple[float, float]] = []
    vals: list[tuple[float, float, float]] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue  # the last line of a killed run
        if not isinstance(rec, dict) or "time" not in rec:
            continue
        if rec.get("event") == "start" and t0 is None:
            t0 = float(rec["time"])
        elif rec.get("event") == "step" and t0 is not None:
            steps.append(((rec["time"] - t0) / 60.0, float(rec["loss"])))
        elif rec.get("event") == "val" and t0 is not None:
            vals.append(
                ((rec["time"] - t0) / 60.0, float(rec["recall_at_1"]), float(rec["recall_at_1pct"]))
            )
    if t0 is None or not steps:
        raise InputError("no start line or no step in the training log", path)
    s = np.asarray(steps)
    v = np.asarray(vals).reshape(-1, 3)
    return Curve(name or path.parent.name, s[:, 0], s[:, 1], v[:, 0], v[:, 1], v[:, 2])


def smoothed(values: np.ndarray, window: int = 20) -> np.ndarray:
    """The trailing mean over ``window`` points (the first points over what there is)."""
    c = np.cumsum(np.insert(np.asarray(values, dtype=np.float64), 0, 0.0))
    n = np.arange(1, len(values) + 1)
    lo = np.maximum(n - window, 0)
    return (c[n] - c[lo]) / (n - lo)


def write_learning_curves(curves: list[Curve], png: str | Path, title: str | None = None) -> Path:
    """One figure: the smoothed loss (left) and validation recall@1 (solid) and recall@1%
    (dashed, right) of every curve against minutes; written to ``png`` via a temporary file."""
    from pnvlad_service.extras import pyplot

    plt = pyplot("learning curves")
    png = Path(png)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for k, c in enumerate(curves):
        color = f"C{k % 10}"
        a.plot(c.minutes, smoothed(c.loss), color=color, label=c.name)
        if len(c.val_minutes):
            b.plot(c.val_minutes, c.recall_at_1, "-o", ms=3, color=color, label=f"{c.name} @1")
            b.plot(c.val_minutes, c.recall_at_1pct, "--", color=color, label=f"{c.name} @1%")
    a.set_xlabel("minutes")
    a.set_ylabel("training loss (mean of 20 logged steps)")
    b.set_xlabel("minutes")
    b.set_ylabel("validation recall (%)")
    for ax in (a, b):
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[1]:
            ax.legend(fontsize=7)
    if not any(len(c.val_minutes) for c in curves):
        b.text(0.5, 0.5, "no validation recorded", ha="center", va="center", transform=b.transAxes)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    tmp = png.with_name(png.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(png)
    return png
