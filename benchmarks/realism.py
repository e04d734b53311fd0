"""How real does the synthetic city look? The same statistics of the real scans and of synthetic
scans of the matching sensor, side by side, with a distance per statistic.

Usage: python benchmarks/realism.py [--preset demo | --tree DIR] [--seed 0] [--scans 12]
       [--real DIR] [--png realism.png] [--preset-sensor] [--ablation]

Real: the scans of ../shared/data/real_scans (or $PNVLAD_REAL_SCANS, or --real), read in
place: six KITTI scans (Velodyne HDL-64E), a nuScenes sweep and an NCLT scan (HDL-32E).
Synthetic: ``--scans`` scans of the city ``pnvlad synth --preset PRESET --seed SEED`` drives (or
the city of a tree it wrote, ``--tree``, from its synth.json), cast again in memory, spread
over the runs and routes of the district most like the real place where the preset has it
(KITTI 00: residential, nuScenes: business, NCLT: campus; ``--preset benchmark`` has all
three, ``demo`` only business); no tree is written. Each real source gets its own
synthetic sensor, the preset's LiDAR with the beams, columns and mount height of the real one
(:data:`SOURCES`): KITTI's HDL-64E (64 beams, +2 to -24.8 degrees, 2,000 columns, 1.73 m), the
nuScenes HDL-32E (32 beams, +10.67 to -30.67, 1,084 columns, 1.84 m) and NCLT's, which is
mounted upside down (its laser ids' elevations run from -10.4 to +30.8 degrees about a point
1.0 m above the frame's origin). ``--preset-sensor`` compares KITTI with the preset's own
sensor instead (what its submaps are made of: the demo casts 64 x 900 rays).

Per scan (pnvlad_service/synth/realism.py), after dropping the returns closer than 2.5 m or
farther than 100 m: points; the sensor's height above the ground plane; the range and height
(about the sensor) of every return; the returns per ring (KITTI: one turn of the azimuth per
beam in file order; nuScenes and NCLT: their ring field; synthetic: the beams); the share of
ground (the filter G's own estimate); the local shape of 5,000 returns' 16-neighbourhoods
(linear, planar or scattered by the PCA eigenvalues). Then through G as a single scan is (50 m
crop, 0.2 m voxels, ground removed): the points G keeps, its leaf size, the share of its output
within 0.2 m of the ground plane, the height and shape of its output.

Distances: the earth mover's distance of distributions (metres, rings), the relative difference
of counts and lengths (%), the difference of shares (percentage points). The table is Markdown,
docs/SYNTH.md's; ``--png`` draws the distributions (matplotlib, the ``plot`` extra).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from entry import real_scans_default, run

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_points
from pnvlad_service.synth import realism as rl

FEATURE = "The realism figure"


@dataclass(frozen=True)
class Source:
    """A real source: its files, how its points become a sensor frame (z ``up`` of the file's,
    then the sensor ``sensor_z`` above the origin), where its rings come from, and the fields of
    the synthetic sensor that matches it (``LidarConfig``, over the preset's)."""

    name: str
    sensor: str
    files: tuple[str, ...]
    reader: str
    rings: str  # "turns" (file order) or "field"
    district: str  # the synthetic district most like the place, where the preset has it
    lidar: dict[str, Any] = field(default_factory=dict)
    up: float = 1.0
    sensor_z: float = 0.0


HDL64E = {"beams": 64, "elevation_max_deg": 2.0, "elevation_min_deg": -24.8}
SOURCES = (
    Source(
        "KITTI",
        "HDL-64E",
        tuple(f"kitti00_{i:06d}.bin" for i in (0, 5, 52, 94, 95, 4501)),
        "kitti",
        "turns",
        "residential",  # KITTI 00: a residential quarter of Karlsruhe
        {**HDL64E, "columns": 2000, "mount_height": 1.73},  # 0.18 degree steps measured
    ),
    Source(
        "nuScenes",
        "HDL-32E",
        ("nuscenes_lidar_top.bin",),
        "nuscenes",
        "field",
        "business",  # Singapore's One-North, Boston's Seaport
        {
            "beams": 32,
            "elevation_max_deg": 10.67,
            "elevation_min_deg": -30.67,
            "columns": 1084,  # 0.33 degree steps (20 Hz)
            "mount_height": 1.84,
        },
    ),
    Source(
        "NCLT",
        "HDL-32E upside down",
        ("nclt_1326652795280148.bin",),
        "nclt",
        "field",
        "campus",  # the University of Michigan's North Campus
        # z points down; the laser ids' elevations agree to 0.07 degrees about a point 1.0 m
        # above the origin, from -10.4 to +30.8 degrees: the sensor is mounted upside down.
        {
            "beams": 32,
            "elevation_max_deg": 30.67,
            "elevation_min_deg": -10.67,
            "columns": 2950,  # 0.122 degree steps measured
            "mount_height": 1.0,
        },
        up=-1.0,
        sensor_z=1.0,
    ),
)


def _ring_field(path: Path, reader: str) -> np.ndarray:
    """The ring (nuScenes) or laser id (NCLT) of each point."""
    if reader == "nuscenes":
        return np.fromfile(path, "<f4").reshape(-1, 5)[:, 4].astype(np.int64)
    if reader == "nclt":
        return np.fromfile(path, np.uint8).reshape(-1, 8)[:, 7].astype(np.int64)
    raise InputError(f"no ring field in the {reader} format", path)


def real_stats(src: Source, root: Path, args: argparse.Namespace) -> rl.ScanStats:
    """The pooled statistics of a real source's scans."""
    layout = rl.Layout(
        src.lidar["beams"], src.lidar["elevation_max_deg"], src.lidar["elevation_min_deg"]
    )
    stats = []
    for name in src.files:
        path = root / name
        pts = read_points(path, src.reader).astype(np.float64)
        pts[:, 2] = src.up * pts[:, 2] - src.sensor_z
        ids = _ring_field(path, src.reader) if src.rings == "field" else rl.scan_turns(pts)
        stats.append(rl.scan_stats(pts, layout, ring_ids=ids, k=args.k, sample=args.sample))
    return rl.pool(stats)


def city(args: argparse.Namespace) -> tuple[Any, int]:
    """The preset and seed of the city: ``--tree``'s synth.json, else ``--preset``/``--seed``."""
    from pnvlad_service.synth.generate import get_preset

    if args.tree is None:
        return get_preset(args.preset), args.seed
    from pnvlad_service.synth.windows import drives_of

    spec, _, _, seed = next(iter(drives_of(args.tree).values()))
    return spec, seed


def synthetic_stats(
    spec: Any, seed: int, src: Source, lidar: dict[str, Any], args: argparse.Namespace
) -> tuple[rl.ScanStats, Any, list[str]]:
    """The pooled statistics of ``args.scans`` synthetic scans cast with the preset's LiDAR
    changed by ``lidar``, that LiDAR and the areas cast: the preset's areas of ``src``'s
    district (all where it has none), scan j from the area j mod A, run j // A mod R, at
    (j + 0.5) / n of its route."""
    from pnvlad_service.synth.generate import simulated_drive

    sensor = matching_sensor(spec, lidar)
    spec = spec.model_copy(update={"lidar": sensor, "lidars": []})
    layout = rl.Layout.of(sensor)
    areas = [i for i, a in enumerate(spec.areas) if a.district == src.district]
    areas = areas or list(range(len(spec.areas)))
    drives: dict[tuple[int, int], Any] = {}
    stats = []
    for j in range(args.scans):
        key = (areas[j % len(areas)], (j // len(areas)) % spec.runs)
        if key not in drives:
            drives[key] = simulated_drive(spec, key[0], key[1], seed)
        drive = drives[key]
        # the beams as cast (an elevation would put a point of the sweep's seam, moved by the
        # vehicle's motion, in another ring)
        pts, rings = drive.scan(int((j + 0.5) / args.scans * len(drive)), rings=True)
        stats.append(
            rl.scan_stats(pts, layout, ring_ids=rings, k=args.k, sample=args.sample, seed=j)
        )
    return rl.pool(stats), sensor, sorted({spec.areas[a].district for a in areas})


def matching_sensor(spec: Any, lidar: dict[str, Any]) -> Any:
    """The synthetic sensor of a real source: the preset's sensor (of its mix, the one with as
    many beams, else the first) with the source's geometry ``lidar`` (beams, elevations,
    columns, mount height); a catalogue sensor keeps its own beam table where the source's
    beams are the same layout (an HDL-64E's two blocks)."""
    from pnvlad_service.synth.sensors import LidarConfig

    pool = spec.lidars or [spec.lidar]
    base = next((s for s in pool if s.beams == lidar.get("beams")), pool[0])
    fields = base.model_dump()
    if base.elevations_deg is not None and base.beams == lidar.get("beams"):
        lidar = {k: v for k, v in lidar.items() if not k.startswith("elevation")}
    else:
        fields["elevations_deg"] = None
    return LidarConfig.model_validate({**fields, **lidar})


def _value(value: float, unit: str) -> str:
    if unit == "":
        return f"{value:,.0f}"
    if unit == "m":
        return f"{value:.2f} m"
    if unit == "%":
        return f"{value:.1f} %"
    return f"{value:.1f}"


def _distance(value: float, unit: str) -> str:
    if unit == "%":
        return f"{value:+.0f} %"
    if unit == "pp":
        return f"{value:+.1f} pp"
    return f"{value:.2f} {unit}"


def table(results: list[tuple[Source, rl.ScanStats, rl.ScanStats, str]]) -> str:
    """The Markdown table: a statistic a row, each source's real, synthetic and distance."""
    head = ["statistic"]
    for src, real, synth, sensor in results:
        head += [f"{src.name} ({real.scans})", f"synthetic {sensor} ({synth.scans})", "distance"]
    rows = [rl.compare(real, synth) for _, real, synth, _ in results]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, first in enumerate(rows[0]):
        cells = [first.label]
        for comparison in rows:
            r = comparison[i]
            cells += [
                _value(r.real, r.unit),
                _value(r.synth, r.unit),
                _distance(r.distance, r.distance_unit),
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _panel_hist(
    ax: Any, real: np.ndarray, synth: np.ndarray, bins: np.ndarray, xlabel: str
) -> None:
    ax.hist(real, bins, density=True, histtype="step", color="k", label="real")
    ax.hist(synth, bins, density=True, histtype="step", color="tab:red", label="synthetic")
    ax.set_xlabel(xlabel)


def figure(results: list[tuple[Source, rl.ScanStats, rl.ScanStats, str]], png: Path) -> None:
    """Per source a column: range, height, returns per ring, local shape (raw and after G)."""
    from pnvlad_service.extras import pyplot

    plt = pyplot(FEATURE)
    fig, axes = plt.subplots(4, len(results), figsize=(4.2 * len(results), 12), squeeze=False)
    for col, (src, real, synth, sensor) in enumerate(results):
        ax = axes[:, col]
        ax[0].set_title(f"{src.name} {src.sensor} vs synthetic {sensor}", fontsize=9)
        _panel_hist(ax[0], real.ranges, synth.ranges, np.arange(0, 101, 2.0), "range (m)")
        _panel_hist(ax[1], real.heights, synth.heights, np.arange(-4, 12.1, 0.25), "z (m)")
        for counts, colour, name in (
            (real.ring_counts, "k", "real"),
            (synth.ring_counts, "tab:red", "synthetic"),
        ):
            ax[2].step(
                np.arange(len(counts)), counts / counts.sum(), color=colour, where="mid", label=name
            )
        ax[2].set_xlabel("ring (0 = top)")
        x = np.arange(6)
        ax[3].bar(x - 0.2, [*real.shape, *real.g_shape], 0.4, color="k", label="real")
        ax[3].bar(x + 0.2, [*synth.shape, *synth.g_shape], 0.4, color="tab:red", label="synthetic")
        ax[3].set_xticks(x, [*rl.SHAPES, *(f"G {s}" for s in rl.SHAPES)], rotation=30, fontsize=8)
        ax[0].legend(fontsize=8)
    axes[0, 0].set_ylabel("density")
    axes[1, 0].set_ylabel("density")
    axes[2, 0].set_ylabel("share of returns")
    axes[3, 0].set_ylabel("share of neighbourhoods")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)
    plt.close(fig)


def ablation_steps(spec: Any) -> list[tuple[str, Any]]:
    """The realistic ``spec`` (the ``benchmark`` preset) reached from its ``_v1`` in steps of
    one change each (#37): the real beam tables alone (failures off), then the sensors'
    failures, street detail and vehicle shapes, the vehicle's own roof in the lowest beams,
    ground cover and structures (grass, bridges, building fronts), and hills with the sensor
    leaning on them."""
    from pnvlad_service.synth.generate import get_preset
    from pnvlad_service.synth.sensors import REAL_FAILURES, LidarConfig

    def roofless(drop: Any) -> list[Any]:
        """The preset's sensors without their roofs, the fields ``drop`` at their defaults."""
        out = []
        for sensor in spec.lidars:
            fields = sensor.model_dump()
            fields.update(
                {k: LidarConfig.model_fields[k].default for k in (*drop, "ego_roof_drop")}
            )
            out.append(LidarConfig.model_validate(fields))
        return out

    old = get_preset(f"{spec.name}_v1")
    flat = spec.conditions.model_copy(update={"follow_ground": False})
    covers = ("grass_verges", "lawns", "bridges_per_km", "facade_bays", "balconies")
    detail = spec.city.model_copy(update=dict.fromkeys((*covers, "hills"), 0.0))
    covered = spec.city.model_copy(update={"hills": 0.0})
    street = spec.model_copy(update={"lidars": roofless(()), "conditions": flat, "city": detail})
    roofed = street.model_copy(update={"lidars": spec.lidars})
    return [
        ("v1", old),
        ("beam tables", old.model_copy(update={"lidars": roofless(REAL_FAILURES)})),
        ("sensor failures", old.model_copy(update={"lidars": roofless(())})),
        ("street detail", street),
        ("own roof", roofed),
        ("grass and structures", roofed.model_copy(update={"city": covered})),
        ("hills", spec),
    ]


def ablation(spec: Any, seed: int, reals: dict[str, Any], args: argparse.Namespace) -> str:
    """Each statistic's distance to the real scans at every step of :func:`ablation_steps`,
    per source (Markdown)."""
    steps = ablation_steps(spec)
    dist: dict[str, list[list[str]]] = {}
    for _, variant in steps:
        for j, src in enumerate(SOURCES):
            synth, _, _ = synthetic_stats(variant, seed, src, src.lidar, args)
            for r in rl.compare(reals[src.name], synth):
                dist.setdefault(r.label, [[] for _ in SOURCES])[j].append(
                    _distance(r.distance, r.distance_unit)
                )
    names = " → ".join(name for name, _ in steps)
    head = ["statistic", *(f"{src.name}: {names}" for src in SOURCES)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, per_source in dist.items():
        cells = [" → ".join([*v[:-1], f"**{v[-1]}**"]) for v in per_source]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _args() -> argparse.Namespace:
    default = real_scans_default()
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="demo", help="the city of this pnvlad synth preset")
    ap.add_argument("--seed", type=int, default=0, help="and seed")
    ap.add_argument("--tree", type=Path, help="or the city of this pnvlad synth tree (synth.json)")
    ap.add_argument("--scans", type=int, default=12, help="synthetic scans per sensor")
    ap.add_argument("--real", type=Path, default=Path(default), help="the real scans' folder")
    ap.add_argument("--png", type=Path, help="draw the distributions to this PNG")
    ap.add_argument(
        "--preset-sensor", action="store_true", help="KITTI against the preset's own LiDAR"
    )
    ap.add_argument(
        "--ablation",
        action="store_true",
        help="also print each distance at every step from PRESET_v1 to PRESET (#37)",
    )
    ap.add_argument("--k", type=int, default=rl.DEFAULT_K, help="neighbours of a local shape")
    ap.add_argument("--sample", type=int, default=rl.DEFAULT_SAMPLE, help="local shapes per scan")
    return ap.parse_args()


def main() -> int:
    args = _args()
    if args.png is not None:  # fail now, not after the work
        from pnvlad_service.extras import pyplot

        pyplot(FEATURE)
    if not (args.real / SOURCES[0].files[0]).is_file():
        raise InputError("the real scans are not there (--real or $PNVLAD_REAL_SCANS)", args.real)
    t0 = time.perf_counter()
    spec, seed = city(args)
    results = []
    for src in SOURCES:
        lidar = {} if (args.preset_sensor and src.name == "KITTI") else src.lidar
        synth, sensor, districts = synthetic_stats(spec, seed, src, lidar, args)
        label = f"{sensor.beams}x{sensor.columns}, {'/'.join(districts)}"
        results.append((src, real_stats(src, args.real, args), synth, label))
    print(
        f"city: preset {spec.name}, seed {seed}; {time.perf_counter() - t0:.0f} s", file=sys.stderr
    )
    print(table(results))
    if args.png is not None:
        figure(results, args.png)
    if args.ablation:
        reals = {src.name: real for src, real, _, _ in results}
        print("\n" + ablation(spec, seed, reals, args))
    return 0


if __name__ == "__main__":
    run(main)
