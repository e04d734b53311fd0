"""How real the synthetic city looks: the same statistics of real and synthetic scans, and one
distance per statistic (``benchmarks/realism.py`` prints them; docs/SYNTH.md, "Realism").

Every function takes one scan in its *sensor* frame (metres, z up, the sensor at the origin):

- :func:`scan_stats` gathers a scan's statistics into a :class:`ScanStats`: points in the crop
  window, the sensor's height above the ground plane (:func:`~pnvlad_service.preprocess.ground.
  fit_ground_plane`), the ranges and heights of the returns, the returns per ring, the share
  of ground (G's own ground, :func:`~pnvlad_service.preprocess.filter_g.ground_mask`), the local
  shape of the returns (:func:`local_shape`), then the same after the filter G of a single scan
  (:func:`~pnvlad_service.preprocess.filter_g.scan_config`): the points G keeps before its voxel
  grid, its leaf size, the ground G lets through, the heights and the shape of its output;
- rings come from a scan's ring field (:func:`rings_from_field`) or, with none, from each
  return's elevation and the sensor's nominal beams (:func:`rings_by_elevation`);
- :func:`pool` merges the stats of several scans of one source; :func:`compare` lays a real
  source beside a synthetic one, a :class:`Row` per statistic, with its distance: the earth
  mover's distance (:func:`emd`) of distributions, the relative difference of counts and
  lengths (:func:`relative_difference`), the difference in percentage points of shares.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from pnvlad_service.preprocess.filter_g import GConfig, apply_g, ground_mask, scan_config
from pnvlad_service.preprocess.ground import fit_ground_plane

#: The local shapes, in the order of :func:`local_shape`'s columns.
SHAPES = ("linear", "planar", "scattered")
#: Neighbours of each point's neighbourhood, and the points whose neighbourhood is looked at.
DEFAULT_K = 16
DEFAULT_SAMPLE = 5000
#: Returns closer or farther than this from the sensor are left out (metres): the synthetic
#: sensor's window, which also drops the no-return zeros some formats keep (nuScenes).
DEFAULT_CROP = (2.5, 100.0)
#: Output points of G this close to the raw scan's ground plane count as ground let through (m).
GROUND_LEFT_M = 0.2


@dataclass(frozen=True)
class Layout:
    """A spinning sensor's nominal beams: ``beams`` elevations evenly spread from
    ``elevation_max_deg`` (beam 0) down to ``elevation_min_deg``, or the model's own ``table``
    (degrees), as the synthetic LiDAR casts them
    (:func:`~pnvlad_service.synth.lidar.ray_bundle`)."""

    beams: int
    elevation_max_deg: float
    elevation_min_deg: float
    table: tuple[float, ...] | None = None

    @classmethod
    def of(cls, cfg: Any) -> Layout:
        """The layout of a :class:`~pnvlad_service.synth.sensors.LidarConfig`."""
        table = None if cfg.elevations_deg is None else tuple(cfg.elevations())
        return cls(cfg.beams, cfg.elevation_max_deg, cfg.elevation_min_deg, table)

    def elevations(self) -> np.ndarray:
        """float64 [beams], degrees, beam 0 (the top) first."""
        if self.table is not None:
            return np.sort(np.asarray(self.table, dtype=np.float64))[::-1].copy()
        return np.linspace(self.elevation_max_deg, self.elevation_min_deg, self.beams)


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Each point's elevation seen from the origin, float64 [N] degrees (0: level, up > 0)."""
    p = np.asarray(points, dtype=np.float64)
    return np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))


def rings_by_elevation(points: np.ndarray, layout: Layout) -> np.ndarray:
    """Each point's ring, int64 [N] (0: the top beam), as the nominal beam nearest its
    elevation: exact for the synthetic sensor, an estimate for a real one whose beams are not
    evenly spread (an HDL-64E's upper block is denser than its lower)."""
    table = layout.elevations()
    if layout.beams == 1:
        return np.zeros(len(points), np.int64)
    el = elevation_deg(points)
    if layout.table is not None:  # the nearest of the table's beams (descending)
        mids = (table[:-1] + table[1:]) / 2
        return np.searchsorted(-mids, -el).astype(np.int64)
    step = (table[0] - table[-1]) / (layout.beams - 1)
    ring = np.rint((table[0] - el) / step)
    return np.clip(ring, 0, layout.beams - 1).astype(np.int64)


def rings_from_field(ids: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rings int64 [N] from a scan's ring or laser-id field ``ids`` [N]: the ids ranked by the
    median elevation of their points, 0 the highest. Formats number their lasers their own way
    (nuScenes from the bottom, NCLT in the HDL-32E's firing order)."""
    ids = np.asarray(ids).astype(np.int64)
    el = elevation_deg(points)
    present = np.unique(ids)
    median = np.array([np.median(el[ids == i]) for i in present])
    rank = np.empty(len(present), np.int64)
    rank[np.argsort(-median, kind="stable")] = np.arange(len(present))
    return rank[np.searchsorted(present, ids)]


def scan_turns(points: np.ndarray) -> np.ndarray:
    """Which turn of the azimuth each point belongs to, int64 [N] (0: the first), for files that
    store a spinning sensor's beams one after the other, each over one turn (KITTI): the
    azimuth, unwrapped along the file, counts the turns. Give them to :func:`rings_from_field`
    as ring ids (on the real KITTI scans here: 64 turns, the beams' median elevations falling
    from +2.6 to -23.7 degrees)."""
    p = np.asarray(points, dtype=np.float64)
    turns = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
    return np.floor((turns - turns[0]) / (2 * np.pi) + 1e-3).astype(np.int64)


def local_shape(
    points: np.ndarray,
    *,
    k: int = DEFAULT_K,
    sample: int = DEFAULT_SAMPLE,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Linearity, planarity, scattering (float64 [M, 3]) of the neighbourhoods of ``sample``
    points drawn from ``points`` (all of them when fewer), each the ``k`` nearest points of the
    whole cloud: with the covariance's eigenvalues l1 >= l2 >= l3, ``(l1 - l2) / l1``,
    ``(l2 - l3) / l1`` and ``l3 / l1`` (they sum to 1; models/local_shape.py's definitions).
    A neighbourhood with no extent gets zeros."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if n < 3:
        return np.zeros((0, 3))
    rng = np.random.default_rng(0) if rng is None else rng
    at = np.arange(n) if n <= sample else np.sort(rng.choice(n, sample, replace=False))
    _, nb = cKDTree(pts).query(pts[at], k=min(k, n))
    hood = pts[nb]
    hood = hood - hood.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", hood, hood) / hood.shape[1]
    ev = np.clip(np.linalg.eigvalsh(cov)[:, ::-1], 0.0, None)
    out = np.zeros((len(at), 3))
    l1 = ev[:, 0]
    ok = l1 > 1e-12
    out[ok, 0] = (ev[ok, 0] - ev[ok, 1]) / l1[ok]
    out[ok, 1] = (ev[ok, 1] - ev[ok, 2]) / l1[ok]
    out[ok, 2] = ev[ok, 2] / l1[ok]
    return out


def shape_shares(features: np.ndarray) -> np.ndarray:
    """Shares float64 [3] of the neighbourhoods that are mostly linear, planar, scattered (the
    largest of :func:`local_shape`'s three); neighbourhoods with no extent are left out."""
    f = np.asarray(features, dtype=np.float64)
    f = f[f.sum(axis=1) > 0]
    if len(f) == 0:
        return np.full(3, np.nan)
    return np.bincount(np.argmax(f, axis=1), minlength=3) / len(f)


def emd(
    u: np.ndarray,
    v: np.ndarray,
    u_weights: np.ndarray | None = None,
    v_weights: np.ndarray | None = None,
) -> float:
    """The earth mover's (1-D Wasserstein) distance between two samples, in their unit: the
    mean distance a value must move to turn one distribution into the other."""
    from scipy.stats import wasserstein_distance

    return float(wasserstein_distance(u, v, u_weights, v_weights))


def relative_difference(real: float, synth: float) -> float:
    """``(synth - real) / |real|``: signed, -0.5 for half the real value (nan for real 0)."""
    return (synth - real) / abs(real) if real else float("nan")


@dataclass(frozen=True)
class ScanStats:
    """The statistics of one scan, or of several pooled (:func:`pool`); lengths in metres.

    Scalars (means over pooled scans): ``points`` in the crop window, ``sensor_height`` above
    the ground plane, ``ground_share`` (G's ground), ``shape`` [3] (:data:`SHAPES` shares);
    after G: ``g_points`` (what G keeps after its crop, voxels and ground removal, before its
    voxel grid), ``g_leaf`` (its leaf size), ``g_ground_left`` (share of its output within
    :data:`GROUND_LEFT_M` of the raw scan's ground plane), ``g_shape`` [3].
    Samples (pooled): ``ranges``, ``heights`` (z about the sensor) of the returns, ``g_heights``
    of G's output back in metres; ``ring_counts`` int64 [beams] (ring 0 the top; summed).
    """

    scans: int
    points: float
    sensor_height: float
    ground_share: float
    shape: np.ndarray
    g_points: float
    g_leaf: float
    g_ground_left: float
    g_shape: np.ndarray
    ranges: np.ndarray
    heights: np.ndarray
    g_heights: np.ndarray
    ring_counts: np.ndarray


_SAMPLES = ("ranges", "heights", "g_heights")


def _after_g(
    pts: np.ndarray, g: GConfig, normal: np.ndarray, offset: float, k: int, seed: int
) -> dict[str, object]:
    """The ``g_*`` fields of :class:`ScanStats` for one cropped scan."""
    res = apply_g(pts, g, seed=seed)
    back = res.centre + res.scale * res.points  # G's output in the scan's metres
    above = back @ normal + offset
    return {
        "g_points": float(res.n_nonground),
        "g_leaf": float(res.leaf_size),
        "g_ground_left": float(np.mean(np.abs(above) < GROUND_LEFT_M)),
        "g_shape": shape_shares(local_shape(back, k=k, sample=len(back))),
        "g_heights": back[:, 2].astype(np.float32),
    }


def scan_stats(
    points: np.ndarray,
    layout: Layout,
    *,
    ring_ids: np.ndarray | None = None,
    crop: tuple[float, float] = DEFAULT_CROP,
    g: GConfig | None = None,
    k: int = DEFAULT_K,
    sample: int = DEFAULT_SAMPLE,
    seed: int = 0,
) -> ScanStats:
    """The statistics of one scan: ``points`` float [N, 3] in its sensor frame (metres, z up,
    the sensor at the origin), ``layout`` its sensor's nominal beams, ``ring_ids`` [N] its ring
    field or its turns (:func:`scan_turns`) where it has them (else rings come from the
    elevations, :func:`rings_by_elevation`); returns outside ``crop`` (m from the sensor) are
    left out first. ``g``: the filter G (default :func:`scan_config`, G of a
    single scan). ``InputError`` when G finds too few points."""
    pts = np.asarray(points, dtype=np.float64)
    rng_m = np.linalg.norm(pts, axis=1)
    keep = (rng_m >= crop[0]) & (rng_m <= crop[1])
    pts, rng_m = pts[keep], rng_m[keep]
    if ring_ids is None:
        rings = rings_by_elevation(pts, layout)
    else:
        rings = rings_from_field(np.asarray(ring_ids)[keep], pts)
    rng = np.random.default_rng(seed)
    normal, offset = fit_ground_plane(pts, rng=rng)
    ground, _ = ground_mask(pts, GConfig(), rng=rng)
    return ScanStats(
        scans=1,
        points=float(len(pts)),
        sensor_height=float(offset),
        ground_share=float(ground.mean()),
        shape=shape_shares(local_shape(pts, k=k, sample=sample, rng=rng)),
        ranges=rng_m.astype(np.float32),
        heights=pts[:, 2].astype(np.float32),
        ring_counts=np.bincount(rings, minlength=layout.beams)[: layout.beams],
        **_after_g(pts, g or scan_config(), normal, offset, k, seed),  # type: ignore[arg-type]
    )


def pool(stats: list[ScanStats]) -> ScanStats:
    """Several scans' statistics as one source's: scalars and shares averaged over the scans,
    samples joined, ring counts summed (the scans must share a layout)."""
    if not stats:
        raise ValueError("no scans to pool")
    merged: dict[str, object] = {"scans": sum(s.scans for s in stats)}
    weights = np.array([s.scans for s in stats], dtype=np.float64)
    for f in fields(ScanStats):
        values = [getattr(s, f.name) for s in stats]
        if f.name == "scans":
            continue
        if f.name in _SAMPLES:
            merged[f.name] = np.concatenate(values)
        elif f.name == "ring_counts":
            merged[f.name] = np.sum(values, axis=0)
        else:
            mean = np.average(np.asarray(values, dtype=np.float64), axis=0, weights=weights)
            merged[f.name] = float(mean) if mean.ndim == 0 else mean
    return replace(stats[0], **merged)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Row:
    """One statistic of a comparison: its label, the real and synthetic values as shown
    (``unit``), the distance and the distance's unit (``%``, ``pp``, ``m``, ``rings``)."""

    label: str
    unit: str
    real: float
    synth: float
    distance: float
    distance_unit: str


def _ring_rows(real: ScanStats, synth: ScanStats) -> Row:
    ri, si = np.arange(len(real.ring_counts)), np.arange(len(synth.ring_counts))
    rc, sc = real.ring_counts.astype(float), synth.ring_counts.astype(float)
    return Row(
        "returns per ring (mean ring, 0 = top)",
        "ring",
        float(ri @ rc / rc.sum()),
        float(si @ sc / sc.sum()),
        emd(ri, si, rc, sc),
        "rings",
    )


def _distribution(label: str, real: np.ndarray, synth: np.ndarray) -> Row:
    return Row(label, "m", float(np.mean(real)), float(np.mean(synth)), emd(real, synth), "m")


def _scalar(label: str, unit: str, real: float, synth: float) -> Row:
    return Row(label, unit, real, synth, 100 * relative_difference(real, synth), "%")


def _share(label: str, real: float, synth: float) -> Row:
    real, synth = float(real), float(synth)
    return Row(label, "%", 100 * real, 100 * synth, 100 * (synth - real), "pp")


def _shapes(prefix: str, real: np.ndarray, synth: np.ndarray) -> list[Row]:
    return [
        _share(f"{prefix}{name} shape", r, y)
        for name, r, y in zip(SHAPES, real, synth, strict=True)
    ]


def compare(real: ScanStats, synth: ScanStats) -> list[Row]:
    """A real source beside a synthetic one, a :class:`Row` per statistic: distributions by
    their mean and earth mover's distance, counts and lengths by their relative difference (%),
    shares by their difference in percentage points; the last rows are after G."""
    rows = [
        _scalar("points per scan", "", real.points, synth.points),
        _scalar("sensor height above the ground", "m", real.sensor_height, synth.sensor_height),
        _distribution("range (mean)", real.ranges, synth.ranges),
        _distribution("height about the sensor (mean)", real.heights, synth.heights),
        _ring_rows(real, synth),
        _share("ground (G's estimate)", real.ground_share, synth.ground_share),
        *_shapes("", real.shape, synth.shape),
        _scalar("G: points kept (0.2 m voxels, no ground)", "", real.g_points, synth.g_points),
        _scalar("G: leaf size", "m", real.g_leaf, synth.g_leaf),
        _share("G: ground left", real.g_ground_left, synth.g_ground_left),
        _distribution("G: height about the sensor (mean)", real.g_heights, synth.g_heights),
        *_shapes("G: ", real.g_shape, synth.g_shape),
    ]
    return rows
