"""Metric registration of a query cloud against a retrieved candidate (issue #10, verified
metric localisation): the transform that lays the query onto the candidate submap, and a score
that tells a true match from a false one.

Why these pieces:

- **Any heading.** Queries come from runs driving either way and from raw scans in the sensor
  frame, so the yaw between query and candidate can be anything. GICP converges only from
  within some 20 degrees, and running it from many yaws costs too much. So each cloud gets a
  bird's-eye occupancy image; the magnitude of its 2-D Fourier transform does not change when
  the cloud is shifted and turns with it, so a circular cross-correlation of the magnitudes
  over angle (on a polar grid) gives the yaw modulo 180 degrees, translation-free (the
  Fourier-Mellin idea, without the scale). Each yaw candidate (and its 180-degree twin) is
  then placed by phase correlation of the images, which also scores it; only the best
  hypotheses go to GICP.
- **GICP by small_gicp.** Coarse (wide correspondence distance, coarser voxels), then fine.
  It was the most accurate and fastest of the libraries measured (docs/VERIFY.md,
  benchmarks/registration.py), and it keeps preprocessing apart from the registration call:
  :func:`prepare` downsamples a cloud and computes its covariances, kd-tree and spectra once,
  so one query is registered against K candidates without redoing its part.
- **Score.** :attr:`Registration.fitness` is the fraction of the (downsampled) query points
  with a candidate point within ``inlier_m`` after alignment: near 1 for the same place, low
  for another one.

Clouds are float [N, 3] metres, z up, in any frame whose origin is near the cloud's middle
(a submap's centre, a scan's sensor). Transforms are float64 4x4, source -> target.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy import ndimage

from pnvlad_service.extras import require


@dataclass(frozen=True)
class RegistrationConfig:
    """Every setting of :func:`prepare` and :func:`register`; lengths in metres.

    Defaults were measured on synthetic submap pairs and a KITTI scan pair
    (benchmarks/registration.py, docs/VERIFY.md).
    """

    fine_voxel_m: float = 1.0  # downsampling of the clouds the fine GICP stage aligns
    coarse_voxel_m: float = 1.5  # downsampling of the source for the coarse stage
    # The coarse cloud voxelised from the fine one rather than from every point: on a full
    # scan the second pass over every point is most of what the coarse cloud costs (KITTI 00's
    # 121,618 points: 1.3 ms from the fine 0.5 m cloud, 6.4 ms from all of them, 2 idle cores);
    # its voxels' centres move by a fraction of a fine voxel, and it only starts the fine stage.
    coarse_of_fine: bool = False
    neighbours: int = 10  # points per covariance estimate
    method: Literal["GICP", "VGICP"] = "VGICP"  # as accurate as GICP here, 2-3x faster
    vgicp_leaf_m: float = 1.0  # voxel size of VGICP's Gaussian voxel map
    coarse_distance_m: float = 3.0  # correspondence distance of the coarse stage
    fine_distance_m: float = 1.0  # ... and of the fine stage
    # 0: no coarse stage after a given init, and no coarse cloud prepared without the yaw
    # search (a start already within centimetres).
    coarse_iterations: int = 6
    fine_iterations: int = 10
    inlier_m: float = 0.5  # a source point within this of the target counts for fitness
    # small_gicp's OpenMP threads per call. Its Python binding holds the GIL, so threads of
    # Python gain nothing (measured: 0.93x); its own threads do (preprocessing 1.8x, alignment
    # 1.5x on 2 idle cores).
    threads: int = 2
    bev_cell_m: float = 1.0  # bird's-eye image cell (the yaw and shift search)
    # Image side; covers +-bev_cells * bev_cell_m / 2 about the origin. 128 cells of 1 m see
    # the whole of a submap (they reach about 80 m): with 64 the search saw +-32 m and failed
    # a quarter of true pairs 15-25 m apart (benchmarks/registration_by_distance.py, VERIFY.md).
    bev_cells: int = 128
    polar_angles: int = 90  # angular bins over 180 degrees in the spectrum's polar grid
    yaw_peaks: int = 2  # yaw-correlation peaks kept (each also tried turned by 180 degrees)
    whitening: float = 0.5  # phase correlation: cross spectrum divided by its magnitude**this
    search_radius_m: float = 64.0  # the yaw and shift search looks at points within this
    hypotheses: int = 1  # best-scoring (yaw, shift) hypotheses given to the coarse GICP
    # The bird's-eye search finds no height: each hypothesis also starts the coarse stage
    # with the clouds' lowest points laid level (this percentile of z, target less source),
    # the start with more coarse inliers kept. Push-broom submaps see facades to different
    # heights, so their centroids (the frames' origins) differ by metres in z, and from a
    # start at 0 the coarse stage slid by a storey (3.3 or 6.6 m) in 23 of 29 true pairs of
    # pushbroom_demo (docs/VERIFY.md). None: the start's z is 0 only.
    level_percentile: float | None = 5.0
    min_points: int = 20  # fewer points is degenerate
    min_spread_m: float = 0.05  # a cloud thinner than this across some axis is degenerate


DEFAULT = RegistrationConfig()


@dataclass(frozen=True, eq=False)
class Prepared:
    """One cloud made ready for :func:`register` by :func:`prepare`.

    ``points``: float64 [N, 3] metres, downsampled at ``fine_voxel_m``; ``reason``: why the
    cloud cannot be registered (see :func:`degenerate`), or None. The rest is small_gicp's
    (clouds with covariances, kd-trees, voxel map) and the yaw search's (image spectra).
    """

    points: np.ndarray
    reason: str | None
    fine: Any = None  # small_gicp.PointCloud with covariances
    coarse: Any = None  # the same at coarse_voxel_m (used as a source)
    tree: Any = None  # small_gicp.KdTree over ``fine``
    voxels: Any = None  # small_gicp.GaussianVoxelMap over ``fine`` (VGICP only)
    spectrum: np.ndarray | None = None  # complex rfft2 of the bird's-eye image
    polar: np.ndarray | None = None  # float [radii, polar_angles], band-passed |FFT|
    # A source's bird's-eye spectra turned by each yaw tried so far, by yaw bin (filled by
    # :func:`place`): the candidates of one query are mostly one place seen at one heading,
    # so their yaw searches ask for the same few turns.
    turned: dict[int, np.ndarray] = field(default_factory=dict, repr=False)


@dataclass(frozen=True)
class Registration:
    """What :func:`register` found.

    ``transform``: float64 4x4 source -> target; ``fitness``: fraction of source points with a
    target point within ``inlier_m`` after alignment (0..1); ``rmse_m``: RMS distance of those
    inliers (nan when none); ``converged``: the fine GICP stage converged; ``init``: how it
    was started ("given", "yaw search", or "none" when nothing ran) and ``init_transform``
    the 4x4 the fine stage started from; ``yaw_deg``: the yaw hypotheses tried;
    ``reason``: why it could not run (a degenerate cloud), else None; ``constraint``: how
    evenly the alignment pins the translation, the smallest over the largest eigenvalue of
    the translational block of the fine stage's Gauss-Newton Hessian (1: equally in every
    direction; near 0: free along some direction, as a straight street's facades leave the
    shift along the street; 0 when nothing ran).
    """

    transform: np.ndarray
    fitness: float
    rmse_m: float
    converged: bool
    init: str
    init_transform: np.ndarray
    yaw_deg: tuple[float, ...] = field(default_factory=tuple)
    reason: str | None = None
    constraint: float = 0.0


def _gicp() -> Any:
    return require("small_gicp", "small-gicp", None, "registration of point clouds")


def degenerate(points: np.ndarray, config: RegistrationConfig = DEFAULT) -> str | None:
    """Why ``points`` [N, 3] (metres) cannot be registered meaningfully, or None.

    Too few points, non-finite values, or a shape that leaves some motion unobservable: all
    on a line (one spread axis) or on a plane (thinner than ``min_spread_m`` across one axis).
    Spreads are the square roots of the covariance's eigenvalues, in metres.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[-1] != 3:
        return f"points must be [N, 3], got shape {list(pts.shape)}"
    if len(pts) < config.min_points:
        return f"{len(pts)} points, at least {config.min_points} needed"
    if not np.isfinite(pts).all():
        return "points hold NaN or infinite values"
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(pts.T)), 0.0, None))[::-1]
    if spread[1] < config.min_spread_m or spread[1] < 1e-3 * spread[0]:
        return f"points lie on a line (spreads {np.round(spread, 3).tolist()} m)"
    if spread[2] < config.min_spread_m or spread[2] < 1e-4 * spread[0]:
        return f"points lie on a plane (spreads {np.round(spread, 3).tolist()} m)"
    return None


def prepare(
    points_m: np.ndarray,
    config: RegistrationConfig = DEFAULT,
    role: Literal["both", "source", "target"] = "both",
    search: bool = True,
) -> Prepared:
    """Downsample ``points_m`` [N, 3] (metres), estimate covariances, build the kd-tree (and
    voxel map for VGICP) and the yaw search's spectra: everything of one cloud that
    :func:`register` needs, done once. A degenerate cloud gives a Prepared with ``reason``.

    ``role``: what the cloud will be. A ``source`` (the query) needs no kd-tree, voxel map or
    image spectrum; a ``target`` (a candidate) no coarse cloud: each skips the other's work.
    ``search`` False: no yaw search's spectra (a cloud only ever registered from a given
    ``init``, as the map's odometry registers its steps)."""
    pts = np.asarray(points_m, dtype=np.float64)
    bad_shape = pts.ndim != 2 or pts.shape[-1] != 3 or len(pts) < config.min_points
    if bad_shape or not np.isfinite(pts).all():  # degenerate() names what is wrong
        return Prepared(points=np.empty((0, 3)), reason=degenerate(pts, config))
    sg = _gicp()
    fine, tree = sg.preprocess_points(
        pts, config.fine_voxel_m, num_neighbors=config.neighbours, num_threads=config.threads
    )
    # The shape checks on the downsampled cloud: as telling (duplicates collapse) and cheaper.
    fine_points = np.ascontiguousarray(fine.points()[:, :3])
    reason = degenerate(fine_points, config)
    if reason is not None:
        if fine.size() < config.min_points:
            reason = (
                f"{fine.size()} distinct points at {config.fine_voxel_m:g} m, at least "
                f"{config.min_points} needed"
            )
        return Prepared(points=np.empty((0, 3)), reason=reason)
    coarse = None
    if role != "target" and (search or config.coarse_iterations > 0):
        coarse, _ = sg.preprocess_points(
            fine_points if config.coarse_of_fine else pts,
            config.coarse_voxel_m,
            num_neighbors=config.neighbours,
            num_threads=config.threads,
        )
    voxels = None
    if config.method == "VGICP" and role != "source":
        voxels = sg.GaussianVoxelMap(config.vgicp_leaf_m)
        voxels.insert(fine)
    spectrum = np.fft.rfft2(bev_image(pts, config)) if search else None
    return Prepared(
        points=fine_points,
        reason=None,
        fine=fine,
        coarse=coarse,
        tree=tree if role != "source" else None,
        voxels=voxels,
        spectrum=spectrum if role != "source" else None,
        polar=polar_magnitude(spectrum, config) if spectrum is not None else None,
    )


# --- the yaw and shift search -------------------------------------------------------------


def bev_image(points: np.ndarray, config: RegistrationConfig) -> np.ndarray:
    """float32 [S, S] bird's-eye occupancy (sqrt of the point count per cell), the origin at
    the image centre; axis 0 is x, axis 1 is y."""
    s = config.bev_cells
    points = points[
        np.einsum("ij,ij->i", points[:, :2], points[:, :2]) <= config.search_radius_m**2
    ]
    ij = np.floor(points[:, :2] / config.bev_cell_m).astype(np.int64) + s // 2
    ok = ((ij >= 0) & (ij < s)).all(axis=1)
    counts = np.bincount(ij[ok, 0] * s + ij[ok, 1], minlength=s * s)
    return np.sqrt(counts.reshape(s, s)).astype(np.float32)


def polar_magnitude(spectrum: np.ndarray, config: RegistrationConfig) -> np.ndarray:
    """The log-magnitude of a bird's-eye image's 2-D spectrum on a polar grid, float [R, A]:
    radii from a few cells (the lowest frequencies only say where the mass is) to the Nyquist
    band, angles over [0, 180) degrees (the magnitude of a real image's spectrum is symmetric).
    Shifting the cloud leaves it unchanged; turning the cloud by psi shifts it by psi.

    ``spectrum`` is the image's ``rfft2`` [S, S // 2 + 1]: its columns are the frequencies
    along y from 0 up, which is the half of the plane that angles in [0, 180) reach (y = r sin
    theta >= 0), so the full transform is never needed."""
    s = config.bev_cells
    mag = np.log1p(np.abs(np.fft.fftshift(spectrum, axes=0)))  # row s // 2: zero along x
    radii = np.arange(4, s // 2 - 2, dtype=np.float64)
    theta = np.arange(config.polar_angles) * (np.pi / config.polar_angles)
    rows = s // 2 + radii[:, None] * np.cos(theta)[None, :]  # axis 0: frequency along x
    cols = radii[:, None] * np.sin(theta)[None, :]  # axis 1: frequency along y, >= 0
    polar = ndimage.map_coordinates(mag, [rows, cols], order=1)
    polar -= polar.mean(axis=1, keepdims=True)
    return polar


def yaw_candidates(source: Prepared, target: Prepared, config: RegistrationConfig) -> list[float]:
    """Yaws (radians) that turn ``source`` towards ``target``: the ``yaw_peaks`` best peaks of
    the angular cross-correlation of the polar spectra, each with its 180-degree twin."""
    a = config.polar_angles
    corr = np.fft.irfft(
        (np.fft.rfft(target.polar, axis=1) * np.conj(np.fft.rfft(source.polar, axis=1))).sum(0),
        n=a,
    )
    peaks: list[float] = []
    order = np.argsort(corr)[::-1]
    spacing = max(1, a // 18)  # peaks at least 10 degrees apart
    for k in order:
        if all(min(abs(k - p) % a, a - abs(k - p) % a) >= spacing for p in peaks):
            peaks.append(int(k))
        if len(peaks) == config.yaw_peaks:
            break
    step = np.pi / a
    return [k * step + half for k in peaks for half in (0.0, np.pi)]


def _turned_spectrum(source: Prepared, yaw: float, config: RegistrationConfig) -> np.ndarray:
    """The rfft2 of ``source``'s bird's-eye image turned by ``yaw`` (a yaw-search bin or its
    180-degree twin), computed once per source and bin; a bin whose twin is known is made from
    it (:func:`half_turn_spectrum`: no image, no FFT)."""
    bins = 2 * config.polar_angles
    key = round(yaw / (np.pi / config.polar_angles)) % bins
    spectrum = source.turned.get(key)
    if spectrum is None:
        twin = source.turned.get((key + config.polar_angles) % bins)
        if twin is not None:
            spectrum = half_turn_spectrum(twin, config.bev_cells)
        else:
            spectrum = np.fft.rfft2(bev_image(source.points @ _rot_z(yaw).T, config))
        source.turned[key] = spectrum  # a race only computes it twice
    return spectrum


def half_turn_spectrum(spectrum: np.ndarray, cells: int) -> np.ndarray:
    """The rfft2 of a ``cells`` x ``cells`` bird's-eye image turned by 180 degrees, from the
    image's own rfft2 ``spectrum``.

    Turning the cloud by 180 degrees takes (x, y) to (-x, -y); a point in cell i along an axis
    (i = floor(x / cell) + cells // 2) lands in cell cells - 1 - i, so the turned image is the
    image flipped along both axes. For a real image f and g(n) = f(cells - 1 - n), the DFT is
    G(k) = exp(2 pi i (k1 + k2) / cells) * conj(F(k)), element by element."""
    return _half_turn_phase(spectrum.shape, cells, spectrum.dtype.str) * np.conj(spectrum)


@functools.lru_cache(maxsize=8)
def _half_turn_phase(shape: tuple[int, ...], cells: int, dtype: str) -> np.ndarray:
    k1 = np.arange(shape[0])[:, None]
    k2 = np.arange(shape[1])[None, :]
    return np.exp(2j * np.pi * (k1 + k2) / cells).astype(dtype)


def place(
    source: Prepared, target: Prepared, yaws: Sequence[float], config: RegistrationConfig
) -> list[tuple[np.ndarray, float]]:
    """For each of ``yaws``: the 4x4 (turn by the yaw, then the image shift that best lays
    the source onto the target, by phase correlation) and its score (the correlation peak's
    height over the mean). One inverse FFT for all of them."""
    spectra = np.stack([_turned_spectrum(source, y, config) for y in yaws])
    cross = np.conj(spectra, out=spectra)  # the stack is a copy: conjugate and scale in place
    cross *= target.spectrum[None]
    mag = np.abs(cross)
    mag **= config.whitening  # in place; numpy takes a square root for the default 0.5
    mag += 1e-9
    cross /= mag
    s = config.bev_cells
    corr = np.fft.irfft2(cross, s=(s, s)).reshape(len(yaws), -1)
    peaks = corr.argmax(axis=1)
    heights = corr[np.arange(len(yaws)), peaks]
    means = np.abs(corr).mean(axis=1)
    out = []
    for yaw, flat, height, mean in zip(yaws, peaks, heights, means, strict=True):
        peak = np.unravel_index(int(flat), (s, s))
        shift = [((p + s // 2) % s - s // 2) * config.bev_cell_m for p in peak]
        transform = np.eye(4)
        transform[:3, :3] = _rot_z(yaw)
        transform[:2, 3] = shift
        out.append((transform, float(height / (mean + 1e-12))))
    return out


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --- registration -------------------------------------------------------------------------


def fitness(
    source_points: np.ndarray,
    target: Prepared,
    transform: np.ndarray,
    inlier_m: float,
    threads: int = 1,
) -> tuple[float, float]:
    """(fraction of ``source_points`` [N, 3] whose nearest target point is within ``inlier_m``
    once moved by ``transform``; RMS distance of those inliers in metres, nan when none)."""
    if len(source_points) == 0 or target.tree is None:
        return 0.0, float("nan")
    moved = source_points @ transform[:3, :3].T + transform[:3, 3]
    _, sq = target.tree.batch_nearest_neighbor_search(moved, num_threads=threads)
    sq = np.asarray(sq, dtype=np.float64).reshape(-1)
    inside = sq <= inlier_m**2
    if not inside.any():
        return 0.0, float("nan")
    return float(inside.mean()), float(np.sqrt(sq[inside].mean()))


def _align(
    source_cloud: Any,
    target: Prepared,
    init: np.ndarray,
    distance: float,
    iterations: int,
    config: RegistrationConfig,
) -> Any:
    sg = _gicp()
    if config.method == "VGICP":
        return sg.align(
            target.voxels,
            source_cloud,
            init_T_target_source=init,
            max_correspondence_distance=distance,
            num_threads=config.threads,
            max_iterations=iterations,
        )
    return sg.align(
        target.fine,
        source_cloud,
        target.tree,
        init_T_target_source=init,
        registration_type="GICP",
        max_correspondence_distance=distance,
        num_threads=config.threads,
        max_iterations=iterations,
    )


def _best_start(
    source: Prepared, target: Prepared, config: RegistrationConfig
) -> tuple[np.ndarray, tuple[float, ...]]:
    """The yaw search, then the coarse GICP stage from each of the best hypotheses: the
    coarse result with the highest fitness, and the yaws (degrees) tried."""
    yaws = yaw_candidates(source, target, config)
    placed = sorted(place(source, target, yaws, config), key=lambda p: -p[1])
    starts = [start for start, _ in placed[: config.hypotheses]]
    dz = level_offset(source, target, config)
    if dz != 0.0:
        starts += [_raised(start, dz) for start in starts]
    best, best_fit = np.eye(4), -1
    for start in starts:
        result = _align(
            source.coarse, target, start, config.coarse_distance_m, config.coarse_iterations, config
        )
        # The coarse stage's own inlier count (within its correspondence distance) picks the
        # hypothesis: no extra nearest-neighbour search.
        if result.num_inliers > best_fit:
            best, best_fit = result.T_target_source, result.num_inliers
    return best, tuple(float(np.degrees(y)) for y in yaws)


def level_offset(source: Prepared, target: Prepared, config: RegistrationConfig) -> float:
    """The height (metres) that lays the source's lowest points level with the target's: the
    ``config.level_percentile`` percentile of z, target less source; 0.0 when it is None or
    under ``config.inlier_m`` (the start at 0 already holds it)."""
    if config.level_percentile is None:
        return 0.0
    q = config.level_percentile
    dz = float(np.percentile(target.points[:, 2], q) - np.percentile(source.points[:, 2], q))
    return dz if abs(dz) >= config.inlier_m else 0.0


def _raised(start: np.ndarray, dz: float) -> np.ndarray:
    out = np.array(start, dtype=np.float64)
    out[2, 3] += dz
    return out


def _failed(init: np.ndarray | None, reason: str) -> Registration:
    start = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
    return Registration(start.copy(), 0.0, float("nan"), False, "none", start.copy(), (), reason)


def register(
    source: Prepared | np.ndarray,
    target: Prepared | np.ndarray,
    config: RegistrationConfig = DEFAULT,
    init: np.ndarray | None = None,
) -> Registration:
    """Register ``source`` onto ``target`` (clouds [N, 3] metres, or :func:`prepare`'s output):
    the 4x4 source -> target, the fitness and how it started.

    With ``init`` (float 4x4, source -> target) the coarse and fine GICP stages start from
    it; without, from the yaw search (any heading). Never raises on a degenerate or empty
    cloud: the answer then has fitness 0, ``converged`` False and the ``reason``.
    """
    src = source if isinstance(source, Prepared) else prepare(source, config, "source")
    tgt = target if isinstance(target, Prepared) else prepare(target, config, "target")
    if src.coarse is None and src.reason is None and (init is None or config.coarse_iterations):
        raise ValueError(
            "the source has no coarse cloud: prepared as a target only (role='target'), or "
            "with no coarse stage (coarse_iterations=0) and no yaw search"
        )
    if tgt.tree is None and tgt.reason is None:
        raise ValueError("the target was prepared as a source only (role='source')")
    reason = src.reason or tgt.reason
    if reason is not None:
        return _failed(init, reason)
    if init is None and (src.polar is None or tgt.spectrum is None):
        raise ValueError("a cloud prepared without the yaw search needs an init")
    try:
        if init is None:
            start, yaws, how = *_best_start(src, tgt, config), "yaw search"
        else:
            start, yaws, how = np.asarray(init, dtype=np.float64), (), "given"
            if config.coarse_iterations > 0:
                coarse = _align(
                    src.coarse, tgt, start, config.coarse_distance_m, config.coarse_iterations,
                    config,
                )  # fmt: skip
                start = coarse.T_target_source
        result = _align(
            src.fine, tgt, start, config.fine_distance_m, config.fine_iterations, config
        )
    except (RuntimeError, ValueError) as exc:  # small_gicp's own failures
        return _failed(init, f"registration failed: {exc}")
    transform = np.asarray(result.T_target_source, dtype=np.float64)
    fit, rmse = fitness(src.points, tgt, transform, config.inlier_m, config.threads)
    return Registration(
        transform,
        fit,
        rmse,
        bool(result.converged),
        how,
        np.asarray(start),
        yaws,
        constraint=translation_constraint(np.asarray(result.H)),
    )


def apart(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """How far transform ``a`` is from ``b`` (float [4, 4] each): the metres of ``b^-1 a``'s
    shift and the degrees of its yaw (a registration's result against the step it started
    from, as the map's odometry and the follow's steps gate them)."""
    d = np.linalg.inv(b) @ a
    return float(np.linalg.norm(d[:3, 3])), abs(math.degrees(math.atan2(d[1, 0], d[0, 0])))


def translation_constraint(hessian: np.ndarray) -> float:
    """The smallest over the largest eigenvalue of the translational block of a 6x6
    Gauss-Newton Hessian (small_gicp orders the parameters rotation, then translation): 0 to
    1, 0 for a zero or non-finite Hessian."""
    block = np.asarray(hessian, dtype=np.float64)[3:, 3:]
    if not np.isfinite(block).all():
        return 0.0
    ev = np.linalg.eigvalsh((block + block.T) / 2)
    return float(max(ev[0], 0.0) / ev[-1]) if ev[-1] > 0 else 0.0
