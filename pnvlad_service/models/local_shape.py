"""Local shape features: what each point's neighbourhood looks like, as extra encoder inputs.

PointNet sees every point alone until the pooling, so a wall, a pole and a tree crown that
cover the same space give it the same inputs. LPD-Net (Liu et al., ICCV 2019) showed on the
PointNetVLAD benchmark that handing the network a few hand-made descriptors of each point's
k nearest neighbours lifts recall substantially. This module computes such descriptors, all of
them unchanged by a turn about the vertical, a shift and a uniform scaling of the cloud (the
augmentations of ``training/augment.py``, and the normalisation every submap gets):

====  ===============================================================================
 0    linearity ``(l1 - l2) / l1`` of the neighbourhood's covariance eigenvalues l1 >= l2 >= l3
 1    planarity ``(l2 - l3) / l1``
 2    scattering ``l3 / l1``
 3    ``|n_z|``: the vertical part of the normal (the smallest eigenvalue's direction): 0 on
      walls, 1 on roofs and the ground
 4    ``|d_z|``: the vertical part of the main direction (the largest eigenvalue's): 1 on poles
 5    eigenentropy of ``l / (l1 + l2 + l3)``, divided by ln 3 (0: a line, 1: a ball)
 6    ``log(r_k / median r_k)``: the distance to the k-th neighbour against the cloud's median
      (sparse, distant structure against dense, near structure), clipped to [-3, 3]
====  ===============================================================================

The features describe neighbourhoods at the density of a submap as stored (4096 points): the
encoder computes them from the cloud it is given, and training computes them on each whole
submap before keeping its ``num_points`` subset (``data/dataset.py``), so that both see the
same neighbourhoods. A point whose neighbourhood has no extent (all neighbours at one spot)
gets zeros.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

#: Features a point gets (the rows of the table above).
NUM_FEATURES = 7


def shape_feature_fn(k: int) -> Callable[[np.ndarray], np.ndarray] | None:
    """The per-cloud feature function ``data.dataset.load_clouds`` takes for a model with
    ``local_k = k`` (None for k = 0: coordinates only)."""
    return functools.partial(shape_features, k=k) if k > 0 else None


def shape_features(points: np.ndarray, k: int) -> np.ndarray:
    """float32 [N, NUM_FEATURES] of one cloud float [N, 3] (k nearest neighbours, the point
    itself included; k is cut to N when the cloud is smaller)."""
    from scipy.spatial import cKDTree

    x = np.ascontiguousarray(points, dtype=np.float64)
    n = len(x)
    out = np.zeros((n, NUM_FEATURES), dtype=np.float32)
    k = min(k, n)
    if n == 0 or k < 3:
        return out
    dist, idx = cKDTree(x).query(x, k=k)
    nb = x[idx]  # [N, k, 3]
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.matmul(c.transpose(0, 2, 1), c) / k  # [N, 3, 3]
    lam, normal, main = _eigen3(cov)
    l1, l2, l3 = lam[:, 2], lam[:, 1], lam[:, 0]
    ok = l1 > 1e-12 * max(float(np.max(l1)), 1e-300)
    inv = np.where(ok, 1.0 / np.where(ok, l1, 1.0), 0.0)
    out[:, 0] = (l1 - l2) * inv
    out[:, 1] = (l2 - l3) * inv
    out[:, 2] = l3 * inv
    out[:, 3] = np.where(ok, np.abs(normal[:, 2]), 0.0)
    out[:, 4] = np.where(ok, np.abs(main[:, 2]), 0.0)
    total = lam.sum(axis=1, keepdims=True)
    e = lam / np.where(total > 0, total, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ent = -np.sum(np.where(e > 0, e * np.log(np.where(e > 0, e, 1.0)), 0.0), axis=1)
    out[:, 5] = np.where(ok, ent / np.log(3.0), 0.0)
    rk = dist[:, -1]
    med = float(np.median(rk))
    if med > 0:
        with np.errstate(divide="ignore"):
            out[:, 6] = np.clip(np.log(np.maximum(rk, 1e-300) / med), -3.0, 3.0)
    return out


def with_shape_features(clouds: np.ndarray, k: int, workers: int = 1) -> np.ndarray:
    """float32 [B, N, 3 + NUM_FEATURES]: each cloud of ``clouds`` float [B, N, 3] with its
    features appended (``workers`` threads: the neighbour search and the eigen-decompositions
    release the GIL)."""
    clouds = np.asarray(clouds, dtype=np.float32)
    b, n, _ = clouds.shape
    out = np.empty((b, n, 3 + NUM_FEATURES), dtype=np.float32)
    out[..., :3] = clouds

    def one(i: int) -> None:
        out[i, :, 3:] = shape_features(clouds[i], k)

    if workers <= 1 or b == 1:
        for i in range(b):
            one(i)
    else:
        with ThreadPoolExecutor(min(workers, b)) as pool:
            list(pool.map(one, range(b)))
    return out


def split_inputs(points: Any, k: int) -> tuple[Any, Any]:
    """(xyz [B, N, 3], features [B, N, NUM_FEATURES] or None) of a torch batch ``points``
    [B, N, 3] or [B, N, 3 + NUM_FEATURES] for an encoder with ``local_k = k``.

    With ``k`` 0 the features are None; otherwise they are the given channels 3 onwards, or,
    for bare coordinates, computed here (on the CPU, outside autograd) and returned on the
    points' device and dtype."""
    import torch

    from pnvlad_service.errors import InputError

    c = points.shape[-1]
    if points.dim() != 3 or c not in ((3, 3 + NUM_FEATURES) if k else (3,)):
        want = f"[B, N, 3] or [B, N, 3 + {NUM_FEATURES}]" if k else "[B, N, 3]"
        raise InputError(f"expected points of shape {want}, got {list(points.shape)}", "points")
    if not k:
        return points, None
    if c > 3:
        return points[..., :3], points[..., 3:]
    xyz = points.detach().to("cpu", torch.float32).numpy()
    feats = np.zeros((*xyz.shape[:2], NUM_FEATURES), dtype=np.float32)
    for i, cloud in enumerate(xyz):
        feats[i] = shape_features(cloud, k)
    return points, torch.from_numpy(feats).to(points.device, points.dtype)


def _eigen3(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of symmetric positive semi-definite [N, 3, 3] matrices: the eigenvalues [N, 3]
    ascending, and unit eigenvectors [N, 3] of the smallest and of the largest.

    In closed form, four times faster than ``np.linalg.eigh`` on 4096 matrices: the eigenvalues
    by the trigonometric solution of the characteristic cubic, each eigenvector as the longest
    cross product of two rows of ``cov - l I`` (orthogonal to its row space). Where that
    eigenvalue is repeated (a line's normal, a disc's main direction) there is no unique
    direction and the vector is zero."""
    a, b, c = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    d, e, f = cov[:, 0, 1], cov[:, 1, 2], cov[:, 0, 2]
    q = (a + b + c) / 3
    p = np.sqrt(((a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2 * (d * d + e * e + f * f)) / 6)
    ps = np.where(p > 0, p, 1.0)
    b00, b11, b22 = (a - q) / ps, (b - q) / ps, (c - q) / ps
    b01, b12, b02 = d / ps, e / ps, f / ps
    det = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    )
    phi = np.arccos(np.clip(det / 2, -1.0, 1.0)) / 3
    l1 = q + 2 * p * np.cos(phi)
    l3 = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    lam = np.stack([l3, 3 * q - l1 - l3, l1], axis=1)

    def vector(lv: np.ndarray) -> np.ndarray:
        r0 = np.stack([a - lv, d, f], axis=1)
        r1 = np.stack([d, b - lv, e], axis=1)
        r2 = np.stack([f, e, c - lv], axis=1)
        crosses = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)])  # [3, N, 3]
        sq = (crosses * crosses).sum(axis=2)  # [3, N]
        best = sq.argmax(axis=0)
        rows = np.arange(len(lv))
        v, n2 = crosses[best, rows], sq[best, rows]
        scale = np.where(n2 > 1e-24 * np.maximum(p, 1e-300) ** 4, 1.0 / np.sqrt(n2 + 1e-300), 0.0)
        return v * scale[:, None]

    return lam, vector(l3), vector(l1)
