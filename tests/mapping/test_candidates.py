"""Closure candidates on the tiny city: nearby by the recorded poses, and by retrieval, which
still finds a run's places when its fixes are farther off than the nearby radius."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _nodes(tiny: Path, shift_run: int | None = None, shift_e: float = 0.0):
    from pnvlad_service.mapping.nodes import read_tree_nodes

    nodes = read_tree_nodes(tiny)
    if shift_run is not None:
        nodes.runs[shift_run].poses[:, 0, 3] += shift_e
    return nodes


def test_nearby_candidates_are_other_runs_within_the_radius(tiny: Path) -> None:
    from pnvlad_service.mapping.candidates import CandidateConfig, nearby_candidates, query_nodes

    nodes = _nodes(tiny)
    config = CandidateConfig()
    queries = query_nodes(nodes, config.every)
    assert set(nodes.local[queries] % config.every) == {0}
    found = nearby_candidates(nodes, queries, config)
    xy = nodes.poses[:, :2, 3]
    assert found
    for (q, run), group in found.items():
        assert 1 <= len(group) <= config.nearby
        for g in group:
            assert nodes.run_of[g] == run
            assert np.hypot(*(xy[g] - xy[q])) <= config.radius_m
            if run == nodes.run_of[q]:
                assert abs(int(nodes.local[g]) - int(nodes.local[q])) >= config.min_gap


def test_retrieval_finds_the_places_of_a_run_whose_fixes_are_far_off(tiny: Path) -> None:
    """Run 2's fixes put 15 m east: what is near it by its recorded poses is another place,
    while descriptors that know the place (here the true positions, as a perfect encoder's
    would) propose its true neighbours, and the verification accepts them."""
    from pnvlad_service.mapping.candidates import (
        CandidateConfig,
        merged,
        nearby_candidates,
        query_nodes,
        retrieval_candidates,
    )
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, closure_edges

    nodes = _nodes(tiny, shift_run=2, shift_e=15.0)
    config = CandidateConfig(retrieved=3)
    queries = query_nodes(nodes, config.every)
    queries = queries[nodes.run_of[queries] == 2]
    near = nearby_candidates(nodes, queries, config)
    true_xy = nodes.truth[:, :2, 3]
    for (q, _), group in near.items():  # what the fixes propose is another place
        assert all(np.hypot(*(true_xy[g] - true_xy[q])) >= 5.0 for g in group)
    descriptors = true_xy.astype(np.float32)
    found = retrieval_candidates(nodes, descriptors, queries, config)
    others = {key: g for key, g in found.items() if key[1] != 2}
    assert len(others) >= len(queries)  # about every query finds another run's nodes
    groups = merged(found, per_group=config.per_group)
    edges = EdgeConfig(gate_m=20.0)  # the fixes are 15 m off: the gate must allow it
    closures = closure_edges(nodes, Clouds(nodes, edges), groups, edges)
    accepted = [e for e in closures if e.accepted and nodes.run_of[e.target] != 2]
    assert len(accepted) >= 3
    truth = nodes.truth
    for e in accepted:
        expected = np.linalg.inv(truth[e.target]) @ truth[e.source]
        assert np.linalg.norm(e.transform[:2, 3] - expected[:2, 3]) < 0.5


def test_embedding_the_nodes_with_a_model(tiny: Path, tmp_path: Path) -> None:
    from pnvlad_service.mapping.candidates import embed_nodes
    from tests.index.helpers import make_checkpoint

    nodes = _nodes(tiny)
    desc = embed_nodes(nodes, make_checkpoint(tmp_path / "ckpt"))
    assert desc.shape == (len(nodes), 16) and desc.dtype == np.float32
    assert np.allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-4)
