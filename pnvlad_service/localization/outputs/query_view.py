"""The live view of a server (``pnvlad serve --foxglove``): each answered query as Foxglove's
own schemas, on the map the server loaded at its start (frames and units: :mod:`.step`).

Topics, besides the map's (``/pnvlad/map/entries``, ``/pnvlad/map/cloud``, ``utm`` -> ``map``
on ``/tf``) that :class:`~.foxglove_view.FoxgloveView` sends:

- ``/pnvlad/query/candidates``: PointCloud, the answer's matches (their UTM positions, at
  height 0 in ``map``), best first;
- ``/pnvlad/query/pose``: PoseInFrame, the verified pose (and ``map`` -> ``sensor`` on
  ``/tf``);
- ``/pnvlad/query/answer``: JSON, what the answer says of itself (``mode``, ``verified``,
  ``confidence``, the best match, the stages' milliseconds).

A query carries no sensor time: each is logged at the server's clock when it was answered.
The view reads the answer's JSON (the server's contract), not the localiser's types.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.localization.outputs.foxglove_view import FoxgloveView
from pnvlad_service.localization.outputs.step import MapView

#: ``/pnvlad/query/answer``'s JSON schema.
ANSWER_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "mode": {"type": "string"},
        "verified": {"type": ["boolean", "null"]},
        "confidence": {"type": ["number", "null"]},
        "reason": {"type": ["string", "null"]},
        "top_submap_id": {"type": ["string", "null"]},
        "candidates": {"type": "integer"},
        "total_ms": {"type": ["number", "null"]},
    },
}


class QueryView(FoxgloveView):
    """A server's live view at ``serve`` (host, port), drawing ``view`` (the map loaded)."""

    def __init__(self, serve: tuple[str, int], view: MapView | None) -> None:
        super().__init__(serve, None)
        from foxglove import Channel
        from foxglove import channels as ch

        c = self.context
        self.candidates = ch.PointCloudChannel("/pnvlad/query/candidates", context=c)
        self.query_pose = ch.PoseInFrameChannel("/pnvlad/query/pose", context=c)
        self.query_answer = Channel("/pnvlad/query/answer", schema=ANSWER_SCHEMA, context=c)
        frames = view.frames() if view is not None else None
        if frames is not None:
            self.start(frames, view)

    def answer(self, doc: dict[str, Any]) -> None:
        """Show one answer (its JSON, ``POST /localize``'s)."""
        ns = time.time_ns()
        if not self._started or self.latch.wanted.is_set():
            self.latch.wanted.clear()
            self._log_map(ns)
            self._started = True
        m = self.fg.messages
        matches = doc.get("matches") or []
        if matches:
            utm = np.array([[x["easting"], x["northing"], 0.0] for x in matches])
            self.candidates.log(self._cloud(self.frames.points_to_map(utm), ns), log_time=ns)
        pose = doc.get("pose")
        if pose:
            matrix = self.frames.to_map(np.asarray(pose["transform"], dtype=np.float64))
            self.query_pose.log(m.PoseInFrame(timestamp=self._stamp(ns), frame_id="map",
                                              pose=self._pose(matrix)), log_time=ns)  # fmt: skip
            tf = self._transform(matrix, ns, "map", "sensor")
            self.tf.log(m.FrameTransforms(transforms=[tf]), log_time=ns)
        v = doc.get("verification") or {}
        self.query_answer.log({
            "mode": doc.get("mode"), "verified": doc.get("verified"),
            "confidence": v.get("confidence"), "reason": v.get("reason"),
            "top_submap_id": matches[0].get("submap_id") if matches else None,
            "candidates": len(matches), "total_ms": (doc.get("timings_ms") or {}).get("total"),
        }, log_time=ns)  # fmt: skip


def open_query_view(host_port: str, bundle: str | Path | None) -> QueryView:
    """The view a server at ``host_port`` (``HOST:PORT``) streams to, drawing the bundle at
    ``bundle``; RuntimeError with one line when the port cannot be bound."""
    from pnvlad_service.localization.outputs.foxglove_view import parse_host_port
    from pnvlad_service.localization.outputs.map_view import load_map_view

    view = None if bundle is None else load_map_view(bundle)
    return QueryView(parse_host_port(host_port), view)
