"""PNG previews of a generated tree: the map with every run's trajectory, and what a submap looks
like at each stage (one raw LiDAR scan, the accumulated 20 m window, the 4096 points after G).

Needs matplotlib (the ``plot`` extra), imported lazily.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)


def _plt():
    from pnvlad_service.extras import pyplot

    return pyplot("synth previews")


def _save_png(plt, fig, out_png: str | Path, dpi: int) -> Path:
    """Lay ``fig`` out, write it to ``out_png`` atomically at ``dpi`` and close it."""
    from pnvlad_service.fileio import atomic_open

    fig.tight_layout()
    out_png = Path(out_png)
    with atomic_open(out_png, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi)
    plt.close(fig)
    return out_png


def _summary(root: Path) -> dict:
    p = root / "synth.json"
    if not p.is_file():
        raise InputError("not a synthetic tree (no synth.json)", root)
    return json.loads(p.read_text())


def render_map(root: str | Path, out_png: str | Path, *, seed: int | None = None) -> Path:
    """One panel per area: buildings, trees, streets, each run's trajectory (the CSV positions
    of its training submaps, with their GNSS/INS error) and the test regions."""
    from matplotlib.patches import Polygon, Rectangle

    from pnvlad_service.data.splits import resolve_regions
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.synth.generate import SynthPreset, _world
    from pnvlad_service.synth.world import KIND_BUILDING

    plt = _plt()
    root = Path(root)
    summ = _summary(root)
    spec = SynthPreset.model_validate(summ["preset"])
    seed = summ["seed"] if seed is None else seed
    tree = BenchmarkTree(root)
    fig, axes = plt.subplots(1, len(spec.areas), figsize=(7 * len(spec.areas), 6.5), squeeze=False)
    for ax, area in zip(axes[0], spec.areas, strict=True):
        world = _world(area, seed, spec.city)
        ox, oy = world.origin
        b = world.scene.boxes
        for k in np.flatnonzero(b.kind == KIND_BUILDING):
            c, s = np.cos(b.yaw[k]), np.sin(b.yaw[k])
            hx, hy = b.half[k]
            corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
            rot = corners @ np.array([[c, s], [-s, c]]) + b.center[k] + world.origin
            ax.add_patch(Polygon(rot, closed=True, fc="#9a9a9a", ec="none"))
        e = world.scene.ellipsoids
        ax.scatter(e.center[:, 0] + ox, e.center[:, 1] + oy, s=4, c="#3a8a3a", lw=0)
        for r in world.roads:
            ax.plot(r.points[:, 0] + ox, r.points[:, 1] + oy, c="#e0c080", lw=1.5, zorder=0)
        runs = tree.runs(area.name)
        colors = plt.cm.tab10(np.linspace(0, 1, 10))
        for i, run in enumerate(runs):
            subs = tree.submaps(area.name, run, "train")
            ax.plot(
                [s.easting for s in subs],
                [s.northing for s in subs],
                ".-",
                ms=2,
                lw=0.8,
                c=colors[i % 10],
                label=run,
            )
        reg = resolve_regions(tree, area.name, area.name)
        w = reg.half_size
        for cn, ce in reg.centres:
            ax.add_patch(Rectangle((ce - w, cn - w), 2 * w, 2 * w, fill=False, ec="red", lw=1.2))
        ax.set_title(f"{area.name}: {len(runs)} runs, test regions in red")
        ax.set_aspect("equal")
        ax.set_xlabel("easting (m, UTM)")
        ax.set_ylabel("northing (m, UTM)")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.legend(fontsize=7, loc="lower right")
    return _save_png(plt, fig, out_png, dpi=110)


def render_submap(
    root: str | Path,
    out_png: str | Path,
    *,
    area_index: int = 0,
    run: int = 0,
    submap: int | None = None,
    seed: int | None = None,
) -> Path:
    """A place at each stage: one raw scan (rings, occlusion shadows), the accumulated 20 m
    window before G (ground included), and the 4096-point submap after G (top and side)."""
    from pnvlad_service.data.accumulate import accumulate
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.synth.generate import SynthPreset, simulated_drive

    plt = _plt()
    root = Path(root)
    summ = _summary(root)
    spec = SynthPreset.model_validate(summ["preset"])
    seed = summ["seed"] if seed is None else seed
    drive = simulated_drive(spec, area_index, run, seed)
    tree = BenchmarkTree(root)
    area = spec.areas[area_index].name
    subs = tree.submaps(area, drive.name, "test")
    sub = subs[len(subs) // 3 if submap is None else submap]
    i = int(np.argmin(np.abs(drive.timestamps - sub.timestamp)))
    xy = drive.poses[:, :2, 3]
    near = np.flatnonzero(np.linalg.norm(xy - xy[i], axis=1) <= 10.0)
    scans = {k: drive.scan(int(k)) for k in near}
    window = accumulate(drive.poses, scans, list(near), drive.poses[i, :3, 3])
    raw = scans[i]
    after = read_points(root / sub.path, reader="benchmark")

    fig, ax = plt.subplots(1, 4, figsize=(22, 5.6))
    lim = 60.0
    sel = (np.abs(raw[:, 0]) < lim) & (np.abs(raw[:, 1]) < lim)
    ax[0].scatter(raw[sel, 0], raw[sel, 1], s=0.2, c=raw[sel, 2], cmap="viridis", lw=0)
    ax[0].set_title(f"one raw scan ({len(raw):,} points), top, sensor frame")
    wsel = (np.abs(window[:, 0]) < 35) & (np.abs(window[:, 1]) < 35)
    ax[1].scatter(window[wsel, 0], window[wsel, 1], s=0.1, c=window[wsel, 2], cmap="viridis", lw=0)
    ax[1].set_title(f"{len(near)} scans over 20 m before G ({len(window):,} points), top")
    ax[2].scatter(after[:, 0], after[:, 1], s=1.0, c=after[:, 2], cmap="viridis", lw=0)
    ax[2].set_title("after G: 4096 points, top (normalised)")
    ax[3].scatter(after[:, 0], after[:, 2], s=1.0, c=after[:, 2], cmap="viridis", lw=0)
    ax[3].set_title("after G: side (x, z)")
    for a in ax:
        a.set_aspect("equal")
    for a in ax[2:]:
        a.set_xlim(-1, 1)
    ax[2].set_ylim(-1, 1)
    ax[3].set_ylim(-0.6, 0.6)
    fig.suptitle(
        f"{area} / {drive.name} / {sub.timestamp}: N {sub.northing:.1f}, E {sub.easting:.1f}"
    )
    return _save_png(plt, fig, out_png, dpi=100)


def render_previews(
    root: str | Path, out_dir: str | Path, *, seed: int | None = None
) -> list[Path]:
    """The map and one submap figure per area into ``out_dir``; returns the PNG paths."""
    from pnvlad_service.synth.generate import SynthPreset

    root = Path(root)
    out_dir = Path(out_dir)
    spec = SynthPreset.model_validate(_summary(root)["preset"])
    paths = [render_map(root, out_dir / "map.png", seed=seed)]
    for ai, area in enumerate(spec.areas):
        paths.append(
            render_submap(root, out_dir / f"submap_{area.name}.png", area_index=ai, seed=seed)
        )
    return paths
