"""Losses: each recomputed with plain Python loops over a small batch."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.training.losses import (
    LOSSES,
    get_loss,
    lazy_quadruplet_loss,
    lazy_triplet_loss,
    quadruplet_loss,
    triplet_loss,
)


def sqdist(a: list[float], b: list[float]) -> float:
    return sum((x - y) ** 2 for x, y in zip(a, b, strict=True))


def loop_loss(q, pos, neg, other, *, quad, lazy, hardest=False, alpha=0.5, beta=0.2) -> float:
    """The published formulas, one tuple and one negative at a time (plain Python floats)."""
    q, pos, neg, other = q.tolist(), pos.tolist(), neg.tolist(), other.tolist()
    first_terms, second_terms = [], []
    for b in range(len(q)):
        dpos = [sqdist(q[b], p) for p in pos[b]]
        best = max(dpos) if hardest else min(dpos)
        h1 = [max(0.0, alpha + best - sqdist(q[b], n)) for n in neg[b]]
        h2 = [max(0.0, beta + best - sqdist(other[b], n)) for n in neg[b]]
        first_terms.append(max(h1) if lazy else sum(h1))
        second_terms.append(max(h2) if lazy else sum(h2))
    loss = sum(first_terms) / len(q)
    if quad:
        loss += sum(second_terms) / len(q)
    return loss


def batch(seed: int, b: int = 3, p: int = 2, nn: int = 5, d: int = 4, scale: float = 0.4):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(b, d, generator=g, dtype=torch.float64) * scale
    pos = torch.randn(b, p, d, generator=g, dtype=torch.float64) * scale
    neg = torch.randn(b, nn, d, generator=g, dtype=torch.float64) * scale
    other = torch.randn(b, d, generator=g, dtype=torch.float64) * scale
    return q, pos, neg, other


CASES = [
    (triplet_loss, False, False),
    (lazy_triplet_loss, False, True),
    (quadruplet_loss, True, False),
    (lazy_quadruplet_loss, True, True),
]


@pytest.mark.parametrize(("fn", "quad", "lazy"), CASES)
@pytest.mark.parametrize("hardest", [False, True])
def test_losses_match_python_loops(fn, quad, lazy, hardest) -> None:
    for seed in range(4):
        q, pos, neg, other = batch(seed)
        got = fn(q, pos, neg, other, hardest_positive=hardest)
        want = loop_loss(q, pos, neg, other, quad=quad, lazy=lazy, hardest=hardest)
        assert want > 0  # the random batch has active hinges, so the comparison means something
        assert got.item() == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_hand_worked_case() -> None:
    # 1-D descriptors: q = 0, positives at 0.1 and 0.3, negatives at 0.5 and 1.0, other at 0.8.
    q = torch.tensor([[0.0]])
    pos = torch.tensor([[[0.1], [0.3]]])
    neg = torch.tensor([[[0.5], [1.0]]])
    other = torch.tensor([[0.8]])
    # best pos 0.01; d(q, n) = 0.25, 1.0 -> hinges 0.26, 0; d(o, n) = 0.09, 0.04 -> 0.12, 0.17
    assert triplet_loss(q, pos, neg).item() == pytest.approx(0.26)
    assert lazy_triplet_loss(q, pos, neg).item() == pytest.approx(0.26)
    assert quadruplet_loss(q, pos, neg, other).item() == pytest.approx(0.26 + 0.12 + 0.17)
    assert lazy_quadruplet_loss(q, pos, neg, other).item() == pytest.approx(0.26 + 0.17)
    # hardest positive 0.09: hinges 0.34, 0 and 0.2, 0.25
    got = quadruplet_loss(q, pos, neg, other, hardest_positive=True)
    assert got.item() == pytest.approx(0.34 + 0.2 + 0.25)


@pytest.mark.parametrize(("fn", "quad", "lazy"), CASES)
def test_all_hinges_zero(fn, quad, lazy) -> None:
    q, pos, neg, other = batch(1)
    pos = q.unsqueeze(1) + 0.01 * pos  # positives right on the query
    neg = neg + 10.0  # negatives far from the query and from other_neg
    loss = fn(q, pos, neg, other)
    assert loss.item() == 0.0
    assert loop_loss(q, pos, neg, other, quad=quad, lazy=lazy) == 0.0


def test_mean_over_batch_not_sum() -> None:
    q, pos, neg, other = batch(2, b=1)
    one = lazy_quadruplet_loss(q, pos, neg, other)
    four = lazy_quadruplet_loss(
        q.repeat(4, 1), pos.repeat(4, 1, 1), neg.repeat(4, 1, 1), other.repeat(4, 1)
    )
    assert four.item() == pytest.approx(one.item())


def test_ignore_zero_loss_averages_over_active_tuples() -> None:
    q, pos, neg, _ = batch(3, b=2)
    neg_far = neg.clone()
    neg_far[1] += 10.0  # tuple 1 contributes nothing
    active = triplet_loss(q[:1], pos[:1], neg_far[:1])
    got = triplet_loss(q, pos, neg_far, ignore_zero_loss=True)
    assert got.item() == pytest.approx(active.item(), rel=1e-9)
    assert triplet_loss(q, pos, neg_far).item() == pytest.approx(active.item() / 2, rel=1e-9)


def test_gradients_flow_to_every_input() -> None:
    q, pos, neg, other = (t.clone().requires_grad_(True) for t in batch(4))
    quadruplet_loss(q, pos, neg, other).backward()
    for t in (q, pos, neg, other):
        assert t.grad is not None and t.grad.abs().sum() > 0


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    b=st.integers(1, 4),
    p=st.integers(1, 3),
    nn=st.integers(1, 6),
    name=st.sampled_from(sorted(LOSSES)),
)
def test_registry_matches_loops(seed: int, b: int, p: int, nn: int, name: str) -> None:
    q, pos, neg, other = batch(seed, b=b, p=p, nn=nn, d=3, scale=0.3)
    got = get_loss(name)(q, pos, neg, other, margin=0.4, second_margin=0.1)
    want = loop_loss(
        q,
        pos,
        neg,
        other,
        quad="quadruplet" in name,
        lazy=name.startswith("lazy"),
        alpha=0.4,
        beta=0.1,
    )
    assert got.item() == pytest.approx(want, rel=1e-10, abs=1e-12)


def test_bad_shapes_and_names_raise_input_error() -> None:
    q, pos, neg, other = batch(0)
    with pytest.raises(InputError, match="positives"):
        triplet_loss(q, pos[:, :, :2], neg)
    with pytest.raises(InputError, match="negatives"):
        triplet_loss(q, pos, neg[:2])
    with pytest.raises(InputError, match="other_neg"):
        quadruplet_loss(q, pos, neg, None)
    with pytest.raises(InputError, match="other_neg"):
        quadruplet_loss(q, pos, neg, other[:2])
    with pytest.raises(InputError, match="lazy_quadruplet"):
        get_loss("quad")
