"""The report of ``pnvlad eval --rerank K`` for people: its console lines and its figures
(``verified_pr.png``, ``pose_errors.png``). The figures themselves are computed in
:mod:`.rerank` and :mod:`.rerank_figures`; this module only presents a finished ``rerank``
section."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.evaluation.rerank_figures import SUCCESS_DEG, SUCCESS_M


def summary_lines(rep: dict[str, Any]) -> list[str]:
    """The console lines of a ``rerank`` section."""
    v, m = rep["verified"], rep["metric"]
    k = rep["candidates"]
    lines = [
        f"re-ranking top {k}: recall@1 {rep['recall_at_1_before']:.1f} -> "
        f"{rep['recall_at_1_after']:.1f} % (recall@{k} before {rep['recall_at_k_before']:.1f} %), "
        f"recall@1% {rep['recall_at_1pct_before']:.1f} -> {rep['recall_at_1pct_after']:.1f} %",
    ]
    if m.get("n"):
        lines.append(
            f"metric success (< {SUCCESS_M:g} m, < {SUCCESS_DEG:g} deg) {m['success']:.1f} % of "
            f"{m['n']} true top-1; median error {m['median_translation_m']:.3f} m, "
            f"{m['median_yaw_deg']:.3f} deg"
        )
    r = rep["metric_reversed"]
    if r.get("n"):
        lines.append(
            f"  reversed runs ({rep['n_reversed']} queries): recall@1 "
            f"{rep['recall_at_1_before_reversed']:.1f} -> {rep['recall_at_1_after_reversed']:.1f} "
            f"%, metric success {r['success']:.1f} % of {r['n']}; median "
            f"{r['median_translation_m']:.3f} m, {r['median_yaw_deg']:.3f} deg"
        )
    lines.append(
        f"verified (confidence >= {v['threshold']:.2f}): precision {v['precision']:.1f} % (place), "
        f"{v['pose_precision']:.1f} % (pose < 2 m, 5 deg), coverage {v['coverage']:.1f} % of "
        f"queries, recall {v['recall']:.1f} % of true top-1"
    )
    cal = rep.get("calibration")
    if cal:
        line = (
            f"  threshold chosen on {cal['n_queries']} training-layout queries "
            f"(target {cal['target_precision']:.1f} %)"
        )
        off = cal.get("off_map")
        if off:
            at = cal["at_threshold"]
            line += (
                f" with {off['n_queries']} off the map planned as {100 * off['share']:g} % of "
                f"queries: {at['off_map_accept']:.1f} % of those verified, expected precision "
                f"{at['expected_precision']:.1f} %"
            )
        lines.append(line)
    for area, a in rep.get("per_area", {}).items():
        lines.append(
            f"  {area}: recall@1 {a['recall_at_1_before']:.1f} -> {a['recall_at_1_after']:.1f} %, "
            f"recall@1% {a['recall_at_1pct_before']:.1f} -> {a['recall_at_1pct_after']:.1f} %, "
            f"verified precision {a['verified']['precision']:.1f} % coverage "
            f"{a['verified']['coverage']:.1f} %"
        )
    return lines


def write_figures(rep: dict[str, Any], folder: Path) -> list[Path]:
    """``verified_pr.png`` (precision against coverage and recall over thresholds, test and
    calibration) and ``pose_errors.png`` (translation and yaw error distributions)."""
    from pnvlad_service.extras import pyplot

    plt = pyplot("the re-ranking figures")
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    fig, ax = plt.subplots(figsize=(6, 4.5))
    curves = [("test", rep["pr_curve"])]
    if rep.get("calibration"):
        curves.append(("training layout (chooses)", rep["calibration"]["pr_curve"]))
    for name, curve in curves:
        xs = [c["recall"] for c in curve if c["n_verified"]]
        ys = [c["precision"] for c in curve if c["n_verified"]]
        ax.plot(xs, ys, label=f"{name}: precision vs recall")
    t = rep["verified"]
    ax.plot([t["recall"]], [t["precision"]], "o", label=f"threshold {t['threshold']:.2f}")
    ax.set_xlabel("recall of verified (% of queries with a true top-1)")
    ax.set_ylabel("precision of verified (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out.append(folder / "verified_pr.png")
    fig.savefig(out[-1], dpi=120)
    plt.close(fig)
    errs = np.array([[e[0], e[1]] for e in rep["errors"]]) if rep["errors"] else np.zeros((0, 2))
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, col, name, limit in ((axes[0], 0, "translation error (m)", SUCCESS_M),
                                 (axes[1], 1, "yaw error (deg)", SUCCESS_DEG)):  # fmt: skip
        vals = np.clip(errs[:, col], 0, limit * 2)
        ax.hist(vals, bins=40, color="tab:blue")
        ax.axvline(limit, color="tab:red", ls="--", label=f"success < {limit:g}")
        ax.set_xlabel(f"{name}, clipped at {limit * 2:g}")
        ax.set_ylabel("queries")
        ax.legend(fontsize=8)
    fig.tight_layout()
    out.append(folder / "pose_errors.png")
    fig.savefig(out[-1], dpi=120)
    plt.close(fig)
    return out
