"""Loop-closure candidates: which nodes may show the same place as a query node.

Two sources, merged per (query, other run):

- **Retrieval** (:func:`retrieval_candidates`): pnvlad's own encoder embeds every node and a
  FAISS search gives each query its nearest descriptors in the other runs (and in its own run,
  farther along than ``min_gap``): a place found by what it looks like, wherever the recorded
  poses put it.
- **Nearby by the recorded poses** (:func:`nearby_candidates`): the nodes of the other runs
  within ``radius_m`` of the query's recorded position. The GNSS/INS error is a few metres, so
  this finds every overlap of runs whose fixes are sound, at no cost, model or none; retrieval
  adds the places where the fixes are far off and is what a run without fixes has.

Every candidate is then registered and judged (:mod:`.edges`): a wrong one costs time, never a
bent map.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pnvlad_service.mapping.nodes import MapNodes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CandidateConfig:
    """``every``: one query node every this many nodes of a run (keyframes every 5 m: 4 is a
    query every 20 m); ``radius_m``: nearby candidates within this of the query's recorded
    position; ``nearby``: at most this many of them per other run, nearest first;
    ``retrieved``: descriptors searched per query (the ``top`` nearest across the map);
    ``min_gap``: nodes of the query's own run closer than this many nodes along it are no
    loop; ``per_group``: at most this many candidates verified per (query, run)."""

    every: int = 4
    radius_m: float = 10.0
    nearby: int = 2
    retrieved: int = 10
    min_gap: int = 20
    per_group: int = 4


def query_nodes(nodes: MapNodes, every: int) -> np.ndarray:
    """int [Q]: every ``every``-th node of each run (global indices)."""
    return np.flatnonzero(nodes.local % max(1, every) == 0)


def _other(nodes: MapNodes, q: int, g: int, min_gap: int) -> bool:
    """Whether node ``g`` may close a loop with ``q``: another run, or far along its own."""
    if nodes.run_of[g] != nodes.run_of[q]:
        return True
    return abs(int(nodes.local[g]) - int(nodes.local[q])) >= min_gap


def nearby_candidates(
    nodes: MapNodes, queries: np.ndarray, config: CandidateConfig
) -> dict[tuple[int, int], list[int]]:
    """(query, run) -> the nodes of that run within ``radius_m`` of the query, nearest first
    (at most ``nearby`` a run)."""
    xy = nodes.poses[:, :2, 3]
    tree = cKDTree(xy)
    out: dict[tuple[int, int], list[int]] = defaultdict(list)
    for q in queries:
        near = tree.query_ball_point(xy[q], config.radius_m)
        near = sorted(near, key=lambda g: float(np.hypot(*(xy[g] - xy[q]))))
        for g in near:
            if not _other(nodes, int(q), g, config.min_gap):
                continue
            group = out[(int(q), int(nodes.run_of[g]))]
            if len(group) < config.nearby:
                group.append(int(g))
    return out


def embed_nodes(nodes: MapNodes, model: str | Path, batch_size: int = 32) -> np.ndarray:
    """float32 [N, D]: every node's descriptor by ``model`` (one heading: a map of a model
    that turns its input is searched by its first turn, as the queries here are map entries
    laid alike)."""
    from pnvlad_service.models.embedding import embed_in_chunks
    from pnvlad_service.models.runtimes import load_encoder

    encoder = load_encoder(model)

    def load(start: int, stop: int) -> np.ndarray:
        return np.stack(
            [
                nodes.runs[nodes.run_of[g]].normalised(int(nodes.local[g]))
                for g in range(start, stop)
            ]
        )

    return embed_in_chunks(encoder.embed, len(nodes), load, chunk=batch_size, desc="embedding")


def retrieval_candidates(
    nodes: MapNodes, descriptors: np.ndarray, queries: np.ndarray, config: CandidateConfig
) -> dict[tuple[int, int], list[int]]:
    """(query, run) -> the nodes of that run among the query's ``retrieved`` nearest
    descriptors (exact FAISS search), nearest first; the query's own neighbours along its run
    left out."""
    import faiss

    desc = np.ascontiguousarray(descriptors, dtype=np.float32)
    index = faiss.IndexFlatL2(desc.shape[1])
    index.add(desc)
    k = min(len(desc), config.retrieved + 2 * config.min_gap + 1)
    _, found = index.search(desc[queries], k)
    out: dict[tuple[int, int], list[int]] = defaultdict(list)
    for q, row in zip(queries, found, strict=True):
        kept = [int(g) for g in row if g >= 0 and _other(nodes, int(q), int(g), config.min_gap)]
        for g in kept[: config.retrieved]:
            out[(int(q), int(nodes.run_of[g]))].append(g)
    return out


def merged(
    *sources: dict[tuple[int, int], list[int]], per_group: int
) -> list[tuple[int, list[int]]]:
    """(query, candidate nodes) per (query, run), in query order: the sources' candidates in
    turn (first source first), each node once, at most ``per_group``."""
    keys = sorted({k for s in sources for k in s})
    out = []
    for key in keys:
        group: list[int] = []
        for s in sources:
            for g in s.get(key, []):
                if g not in group:
                    group.append(g)
        out.append((key[0], group[:per_group]))
    return out
