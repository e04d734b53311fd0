"""How real an accumulated cloud looks: the statistics that tell push-broom clouds apart, of real
and synthetic clouds alike (``benchmarks/realism_pushbroom.py`` prints them; docs/SYNTH.md,
"The push-broom sensor").

Every function takes one cloud accumulated along a drive, in metres, z up, any heading, the
ground included (as the real RobotCar clouds beside the project are laid):

- :func:`cloud_stats` gathers a :class:`CloudStats`: points; the share of ground (G's own
  estimate); heights above the ground plane; the metric extent (5th to 95th percentile along
  the cloud's two horizontal principal axes); the push-broom's lines (:func:`scan_lines`: the
  spacing of the lines along the track and of the points within a line, across it); the local
  shapes (:func:`~pnvlad_service.synth.realism.local_shape`); then through the filter G of a
  submap (ground removed, 4096 points, normalised): the height extent and width of its output,
  in its units, and its local shapes;
- :func:`lay_like_real` lays a synthetic cloud as the real ones were laid (a disc about a place
  on the trajectory, randomly downsampled, turned by a random yaw);
- :func:`pool` merges clouds of one source; :func:`compare` gives a
  :class:`~pnvlad_service.synth.realism.Row` per statistic.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from pnvlad_service.preprocess.filter_g import GConfig, apply_g, ground_mask
from pnvlad_service.preprocess.ground import fit_ground_plane
from pnvlad_service.preprocess.voxel import voxel_average
from pnvlad_service.synth.realism import (
    DEFAULT_K,
    SHAPES,
    Row,
    emd,
    local_shape,
    relative_difference,
    shape_shares,
)

#: The real RobotCar clouds: 16,384 points in a disc of 30 m radius, through a voxel grid of
#: about 0.2 m (their nearest neighbours: median 0.19 and 0.20 m, under 1 % closer than 5 cm;
#: the strongest comb in their ground points has a period of 0.200 m, and 0.141 m, the grid's
#: diagonal: the grid, not the scanner's lines).
REAL_POINTS, REAL_RADIUS_M, REAL_LEAF_M = 16_384, 30.0, 0.2
#: Points this close to the ground plane count as ground for the line detector (m), and the
#: detector's window about the cloud's centre (m) and the periods it looks at (m).
LINE_GROUND_M, LINE_RADIUS_M, LINE_PERIODS_M = 0.15, 10.0, (0.05, 1.0)


@dataclass(frozen=True)
class CloudStats:
    """The statistics of one cloud, or of several pooled (:func:`pool`); lengths in metres.

    Scalars (means over pooled clouds, nan-aware): ``points``, ``ground_share``, ``extent``
    [2] (major, minor), ``line_spacing`` (along the track; nan where no lines show),
    ``line_strength`` (the line comb's peak over the mean power), ``across_gap`` (median gap
    between neighbouring points of a line), ``nn_spacing`` (median distance to the nearest
    point), ``shape`` [3], ``g_height`` and ``g_width`` (the
    height extent and the major-axis extent of G's output, its units), ``g_shape`` [3].
    Samples (pooled): ``heights`` above the ground plane.
    """

    clouds: int
    points: float
    ground_share: float
    extent: np.ndarray
    line_spacing: float
    line_strength: float
    across_gap: float
    nn_spacing: float
    shape: np.ndarray
    g_height: float
    g_width: float
    g_shape: np.ndarray
    heights: np.ndarray


def principal_axes(xy: np.ndarray) -> np.ndarray:
    """float64 [2, 2]: the horizontal principal axes of ``xy`` [N, 2] (rows, major first)."""
    c = np.cov((xy - xy.mean(0)).T)
    _, v = np.linalg.eigh(c)
    return v[:, ::-1].T


def extent(xy: np.ndarray) -> np.ndarray:
    """float64 [2]: the 5th-to-95th percentile spread of ``xy`` [N, 2] along its principal axes
    (major, minor), metres: a cloud's size whatever its heading."""
    u = xy @ principal_axes(xy).T
    return np.percentile(u, 95, axis=0) - np.percentile(u, 5, axis=0)


def scan_lines(ground_xy: np.ndarray) -> tuple[float, float, float, np.ndarray]:
    """The push-broom's lines on the ground near the cloud's centre: (spacing along the track,
    m; the comb's strength, its peak power over the mean; the median gap between neighbouring
    points of a line, m; the along-track unit vector [2]).

    The ground points within :data:`LINE_RADIUS_M` of the centre are projected on each
    heading (0.5 degree steps) and binned at 1 cm; where the lines cross the track, the
    projection on the track is a comb whose period is the spacing of the lines: the heading
    and period of the strongest peak of the power spectrum between :data:`LINE_PERIODS_M`."""
    xy = ground_xy[np.hypot(ground_xy[:, 0], ground_xy[:, 1]) < LINE_RADIUS_M]
    best = (0.0, np.nan, np.zeros(2))
    if len(xy) < 50:
        return np.nan, 0.0, np.nan, best[2]
    for th in np.deg2rad(np.arange(0.0, 180.0, 0.5)):
        axis = np.array([np.cos(th), np.sin(th)])
        u = xy @ axis
        h, _ = np.histogram(u, np.arange(u.min(), u.max() + 0.01, 0.01))
        power = np.abs(np.fft.rfft(h - h.mean())) ** 2
        freq = np.fft.rfftfreq(len(h), 0.01)
        band = (freq > 1 / LINE_PERIODS_M[1]) & (freq < 1 / LINE_PERIODS_M[0])
        if not band.any() or power[band].mean() <= 0:
            continue
        k = int(np.argmax(power[band]))
        score = float(power[band][k] / power[band].mean())
        if score > best[0]:
            best = (score, float(1 / freq[band][k]), axis)
    score, period, axis = best
    if not np.isfinite(period):
        return np.nan, 0.0, np.nan, axis
    # the points of each line (the nearest tooth of the comb), their gaps across the track
    u = xy @ axis
    v = xy @ np.array([-axis[1], axis[0]])
    line = np.round((u - u.min()) / period).astype(np.int64)
    order = np.lexsort((v, line))
    same = np.diff(line[order]) == 0
    gaps = np.diff(v[order])[same]
    return period, score, float(np.median(gaps)) if len(gaps) else np.nan, axis


def cloud_stats(
    points: np.ndarray,
    *,
    raw_points: int | None = None,
    g: GConfig | None = None,
    k: int = DEFAULT_K,
    sample: int = 5000,
    seed: int = 0,
) -> CloudStats:
    """The statistics of one cloud float [N, 3] (metres, z up, ground included).
    ``raw_points``: its points before it was downsampled (None: unknown, nan)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    normal, offset = fit_ground_plane(pts, rng=rng)
    height = pts @ normal + offset
    ground, _ = ground_mask(pts, GConfig(), rng=rng)
    spacing, strength, gap, _ = scan_lines(pts[np.abs(height) < LINE_GROUND_M, :2])
    res = apply_g(pts, g or GConfig(), seed=seed)
    out = res.points
    return CloudStats(
        clouds=1,
        points=float("nan") if raw_points is None else float(raw_points),
        ground_share=float(ground.mean()),
        extent=extent(pts[:, :2]),
        line_spacing=spacing,
        line_strength=strength,
        across_gap=gap,
        nn_spacing=float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])),
        shape=shape_shares(local_shape(pts, k=k, sample=sample, rng=rng)),
        g_height=float(np.ptp(out[:, 2])),
        g_width=float(extent(out[:, :2])[0]),
        g_shape=shape_shares(local_shape(out, k=k, sample=len(out))),
        heights=height.astype(np.float32),
    )


def lay_like_real(
    cloud: np.ndarray,
    rng: np.random.Generator,
    radius: float = REAL_RADIUS_M,
    points: int = REAL_POINTS,
    leaf: float = REAL_LEAF_M,
) -> np.ndarray:
    """A cloud laid about a place on its trajectory (its origin) as the real RobotCar clouds
    are: the disc of ``radius`` metres about it, averaged in ``leaf``-metre voxels, ``points``
    of those at random, turned by a random yaw. float64 [min(V, points), 3]."""
    c = np.asarray(cloud, dtype=np.float64)
    c = c[np.hypot(c[:, 0], c[:, 1]) <= radius]
    if leaf > 0 and len(c):
        c = voxel_average(c, leaf)
    if len(c) > points:
        c = c[np.sort(rng.choice(len(c), points, replace=False))]
    a = rng.uniform(0, 2 * np.pi)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return c @ turn.T


def pool(stats: list[CloudStats]) -> CloudStats:
    """Several clouds' statistics as one source's: scalars and shares averaged (nan-aware),
    heights joined."""
    if not stats:
        raise ValueError("no clouds to pool")
    merged: dict[str, object] = {"clouds": sum(s.clouds for s in stats)}
    for f in fields(CloudStats):
        if f.name == "clouds":
            continue
        values = [getattr(s, f.name) for s in stats]
        if f.name == "heights":
            merged[f.name] = np.concatenate(values)
        else:
            arr = np.asarray(values, dtype=np.float64)
            mean = np.nanmean(arr, axis=0) if np.isfinite(arr).any() else arr[0]
            merged[f.name] = float(mean) if np.ndim(mean) == 0 else mean
    return replace(stats[0], **merged)  # type: ignore[arg-type]


def _scalar(label: str, unit: str, real: float, synth: float) -> Row:
    return Row(label, unit, real, synth, 100 * relative_difference(real, synth), "%")


def _share(label: str, real: float, synth: float) -> Row:
    return Row(label, "%", 100 * float(real), 100 * float(synth), 100 * (synth - real), "pp")


def compare(real: CloudStats, synth: CloudStats) -> list[Row]:
    """A real source beside a synthetic one, a :class:`Row` per statistic (distributions by
    their earth mover's distance, counts and lengths by their relative difference, shares in
    percentage points); the last rows are after G."""
    hr, hs = real.heights, synth.heights
    rows = [
        _scalar("points per cloud before downsampling", "", real.points, synth.points),
        _share("ground (G's estimate)", real.ground_share, synth.ground_share),
        Row(
            "height above the ground (mean)",
            "m",
            float(hr.mean()),
            float(hs.mean()),
            emd(hr, hs),
            "m",
        ),
        _scalar(
            "height above the ground, 90th percentile",
            "m",
            float(np.percentile(hr, 90)),
            float(np.percentile(hs, 90)),
        ),
        _scalar("share above 5 m", "%", 100 * float(np.mean(hr > 5)), 100 * float(np.mean(hs > 5))),
        _scalar("extent, major axis (5-95 %)", "m", real.extent[0], synth.extent[0]),
        _scalar("extent, minor axis (5-95 %)", "m", real.extent[1], synth.extent[1]),
        _scalar("line spacing along the track", "m", real.line_spacing, synth.line_spacing),
        _scalar("line comb strength", "", real.line_strength, synth.line_strength),
        _scalar("gap within a line, across the track", "m", real.across_gap, synth.across_gap),
        _scalar("nearest neighbour (median)", "m", real.nn_spacing, synth.nn_spacing),
        *(
            _share(f"{n} shape", r, s)
            for n, r, s in zip(SHAPES, real.shape, synth.shape, strict=True)
        ),
        _scalar("G: height extent (its units)", "g", real.g_height, synth.g_height),
        _scalar("G: width, major axis 5-95 % (its units)", "g", real.g_width, synth.g_width),
        *(
            _share(f"G: {n} shape", r, s)
            for n, r, s in zip(SHAPES, real.g_shape, synth.g_shape, strict=True)
        ),
    ]
    return rows
