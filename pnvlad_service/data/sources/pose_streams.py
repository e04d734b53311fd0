"""Pose time series: interpolation to other times, and trees of transforms (ROS /tf).

:func:`interpolate_poses` gives poses at query times from timed samples, linearly in position
and by slerp in rotation (scipy's ``Rotation``), with a status per query (inside, before, after
the samples, or in a gap longer than allowed). :class:`PoseStream` holds one series;
:class:`TransformTree` holds a /tf tree (each child frame with its parent and its poses in it,
static or timed) and chains the transforms from one frame to another at each query time.
Times are integer nanoseconds; fractions are computed from integer differences, so stamps near
1.7e18 ns lose nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


def rotations(quats: np.ndarray) -> Any:
    """scipy Rotations from [K, 4] x, y, z, w quaternions (ROS order); ValueError on a zero."""
    from scipy.spatial.transform import Rotation

    norms = np.linalg.norm(quats, axis=1)
    if not np.all(np.isfinite(quats)) or np.any(norms < 1e-9):
        raise ValueError("a pose holds a zero or non-finite quaternion")
    return Rotation.from_quat(quats)


def matrices(positions: np.ndarray, rotations: Any) -> np.ndarray:
    m = np.tile(np.eye(4), (len(positions), 1, 1))
    m[:, :3, :3] = rotations.as_matrix()
    m[:, :3, 3] = positions
    return m


#: Codes of :func:`interpolate_poses`' ``status``.
POSE_OK, POSE_BEFORE, POSE_AFTER, POSE_GAP = 0, 1, 2, 3


def interpolate_poses(
    times_ns: np.ndarray,
    positions: np.ndarray,
    quats: np.ndarray,
    query_ns: np.ndarray,
    *,
    max_gap_ns: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_ns``: linear in position, slerp in rotation between the two samples.

    ``times_ns``: int64 [K] strictly increasing; ``positions``: float64 [K, 3]; ``quats``:
    float64 [K, 4] (x, y, z, w); ``query_ns``: int64 [T]. Returns (float64 [T, 4, 4], int8 [T]
    status: :data:`POSE_OK`, :data:`POSE_BEFORE` / :data:`POSE_AFTER` the samples' span, or
    :data:`POSE_GAP` when the two samples around it are more than ``max_gap_ns`` apart). A query
    at a sample's time gets that sample exactly. Poses whose status is not OK are identities.
    """
    from scipy.spatial.transform import Rotation

    t = np.asarray(times_ns, dtype=np.int64)
    q_ns = np.asarray(query_ns, dtype=np.int64)
    out = np.tile(np.eye(4), (len(q_ns), 1, 1))
    status = np.zeros(len(q_ns), dtype=np.int8)
    status[q_ns < t[0]] = POSE_BEFORE
    status[q_ns > t[-1]] = POSE_AFTER
    inside = np.nonzero(status == POSE_OK)[0]
    q = q_ns[inside]
    k = np.searchsorted(t, q, side="right") - 1  # t[k] <= q
    exact = t[k] == q
    k1 = np.minimum(k + 1, len(t) - 1)
    if max_gap_ns is not None:
        gap = ~exact & (t[k1] - t[k] > max_gap_ns)
        status[inside[gap]] = POSE_GAP
        inside, k, k1, q, exact = inside[~gap], k[~gap], k1[~gap], q[~gap], exact[~gap]
    rot = rotations(np.asarray(quats, dtype=np.float64))
    pos = np.asarray(positions, dtype=np.float64)
    # Fractions from integer differences: exact for stamps near 1.7e18 ns.
    span = np.where(exact, 1, t[k1] - t[k]).astype(np.float64)
    alpha = np.where(exact, 0.0, (q - t[k]).astype(np.float64) / span)
    p = pos[k] + alpha[:, None] * (pos[k1] - pos[k])
    r0 = rot[k] if len(k) else Rotation.identity(0)
    if len(k):
        rel = (r0.inv() * rot[k1]).as_rotvec()
        r = r0 * Rotation.from_rotvec(rel * alpha[:, None])
        mats = matrices(p, r)
        mats[exact] = matrices(pos[k[exact]], rot[k[exact]])
        out[inside] = mats
    return out, status


@dataclass
class PoseStream:
    """A pose time series: int64 [K] ns, float64 [K, 3], float64 [K, 4] (x, y, z, w)."""

    times: np.ndarray
    positions: np.ndarray
    quats: np.ndarray

    @classmethod
    def of(cls, rows: list[tuple[int, Sequence[float], Sequence[float]]]) -> PoseStream:
        rows.sort(key=lambda r: r[0])
        t = np.array([r[0] for r in rows], dtype=np.int64)
        keep = np.r_[True, np.diff(t) > 0]  # the first of equal stamps
        p = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3)
        q = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
        return cls(t[keep], p[keep], q[keep])

    def at(self, query_ns: np.ndarray, max_gap_ns: int | None) -> tuple[np.ndarray, np.ndarray]:
        return interpolate_poses(
            self.times, self.positions, self.quats, query_ns, max_gap_ns=max_gap_ns
        )


class TransformTree:
    """Transforms of /tf and /tf_static: each child frame with its parent and its poses in it."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.rows: dict[str, list[tuple[int, Sequence[float], Sequence[float]]]] = {}
        self.static: dict[str, bool] = {}
        self.streams: dict[str, PoseStream] = {}

    def add(
        self,
        parent: str,
        child: str,
        stamp: int,
        transform: Any,
        *,
        static: bool,
    ) -> None:
        """One transform parent <- child (``transform``: ``translation``, ``rotation``)."""
        old = self.parent.setdefault(child, parent)
        if old != parent:
            raise ValueError(f"frame {child!r} has two parents, {old!r} and {parent!r}")
        tr, rot = transform.translation, transform.rotation
        self.rows.setdefault(child, []).append(
            (stamp, (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w))
        )
        if static:
            self.static[child] = True
        else:
            self.static.setdefault(child, False)

    def finish(self) -> TransformTree:
        """Sort the transforms into streams; ValueError on a bad quaternion."""
        for child, rows in self.rows.items():
            if self.static[child]:
                rows = rows[-1:]  # a static transform: the latest one holds at every time
            try:
                rotations(np.array([r[2] for r in rows], dtype=np.float64))
            except ValueError as exc:
                raise ValueError(f"transform {self.parent[child]} <- {child}: {exc}") from None
            self.streams[child] = PoseStream.of(list(rows))
        return self

    def frames(self) -> list[str]:
        return sorted(set(self.parent) | set(self.parent.values()))

    def _up(self, frame: str) -> list[str]:
        """``frame`` and its ancestors, up to the root."""
        path = [frame]
        while path[-1] in self.parent and len(path) <= len(self.parent):
            path.append(self.parent[path[-1]])
        return path

    def has_path(self, a: str, b: str) -> bool:
        return a == b or bool(set(self._up(a)) & set(self._up(b)))

    def _to_ancestor(
        self, frame: str, ancestor: str, query: np.ndarray, gap: int | None
    ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """ancestor <- frame at each query time, worst status and the dynamic edges' span."""
        total = np.tile(np.eye(4), (len(query), 1, 1))
        status = np.zeros(len(query), dtype=np.int8)
        lo, hi = -(2**62), 2**62
        f = frame
        while f != ancestor:
            stream = self.streams[f]
            if self.static[f]:
                edge = matrices(stream.positions[-1:], rotations(stream.quats[-1:]))
            else:
                edge, st = stream.at(query, gap)
                status = np.maximum(status, st)
                lo, hi = max(lo, int(stream.times[0])), min(hi, int(stream.times[-1]))
            total = edge @ total
            f = self.parent[f]
        return total, status, (lo, hi)

    def chain(
        self, fixed: str, frame: str, query: np.ndarray, gap: int | None
    ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """fixed <- frame at each query time: (float64 [T, 4, 4], status [T], span ns)."""
        up_frame = self._up(frame)
        common = next(f for f in self._up(fixed) if f in up_frame)
        a, status, span = self._to_ancestor(frame, common, query, gap)
        if fixed != common:  # the fixed frame hangs below the common ancestor: go down to it
            b, sb, span_b = self._to_ancestor(fixed, common, query, gap)
            a = np.linalg.inv(b) @ a
            status = np.maximum(status, sb)
            span = (max(span[0], span_b[0]), min(span[1], span_b[1]))
        if span == (-(2**62), 2**62):  # static transforms only
            span = (int(query.min()), int(query.max()))
        return a, status, span
