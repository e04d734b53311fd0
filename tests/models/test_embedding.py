"""models.embedding: chunked embedding fills every row in order; a module embeds in eval mode."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pnvlad_service.models.embedding import embed_in_chunks, module_embedder


class _BatchStats(torch.nn.Module):
    """Output depends on batch norm's mode: wrong in training mode, so eval mode shows."""

    def __init__(self) -> None:
        super().__init__()
        self.bn = torch.nn.BatchNorm1d(3)
        self.fc = torch.nn.Linear(3, 4)
        with torch.no_grad():
            self.bn.running_mean.fill_(0.5)
            self.bn.running_var.fill_(4.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.bn(x.mean(dim=1)))


@pytest.mark.parametrize(("count", "chunk"), [(10, 4), (10, 10), (10, 1), (7, 256)])
def test_chunks_fill_rows_in_order(count: int, chunk: int) -> None:
    rng = np.random.default_rng(count * 31 + chunk)
    clouds = rng.standard_normal((count, 5, 3)).astype(np.float32)
    calls: list[tuple[int, int]] = []

    def load(start: int, stop: int) -> np.ndarray:
        calls.append((start, stop))
        return clouds[start:stop]

    got = embed_in_chunks(lambda x: x.sum(axis=1), count, load, chunk=chunk)
    want = np.stack([clouds[i].sum(axis=0) for i in range(count)])  # one cloud at a time
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert got.dtype == np.float32
    # every cloud loaded exactly once, no chunk larger than asked
    assert [i for s, e in calls for i in range(s, e)] == list(range(count))
    assert max(e - s for s, e in calls) <= chunk


def test_nothing_to_embed_is_empty() -> None:
    assert embed_in_chunks(lambda x: x, 0, lambda s, e: np.zeros((0, 1, 3))).shape == (0, 0)


def test_module_embedder_uses_eval_mode_and_restores_it() -> None:
    torch.manual_seed(0)
    model = _BatchStats()
    model.train()
    x = torch.randn(9, 6, 3)
    embed = module_embedder(model, batch=4)
    got = embed(x.numpy())
    assert model.training  # the caller's mode is back
    model.eval()
    with torch.no_grad():
        want = np.stack([model(x[i : i + 1])[0].numpy() for i in range(len(x))])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    model.train()
    with torch.no_grad():
        in_train_mode = model(x).numpy()
    assert not np.allclose(in_train_mode, want, atol=1e-3)  # the mode matters for this model


def test_quarter_turns_are_exact_and_a_turned_embedder_lays_them_side_by_side() -> None:
    from pnvlad_service.models.embedding import quarter_turn, turned_embedder

    rng = np.random.default_rng(2)
    pts = rng.normal(size=(3, 50, 3)).astype(np.float32)
    assert quarter_turn(pts, 0) is pts
    one = quarter_turn(pts, 1)
    np.testing.assert_array_equal(one[..., 0], -pts[..., 1])  # exact: no trigonometry
    np.testing.assert_array_equal(one[..., 1], pts[..., 0])
    np.testing.assert_array_equal(one[..., 2], pts[..., 2])
    np.testing.assert_array_equal(quarter_turn(quarter_turn(pts, 3), 1), pts)
    np.testing.assert_array_equal(quarter_turn(pts, 2), quarter_turn(one, 1))

    def first_point(x: np.ndarray) -> np.ndarray:  # a "descriptor" that shows the turn
        return x[:, 0, :].astype(np.float32)

    for turns in (1, 2, 4):
        fn = turned_embedder(first_point, turns)
        out = fn(pts)
        assert out.shape == (3, 3 * turns) and getattr(fn, "turns", 1) == turns
        for k in range(turns):
            want = quarter_turn(pts, k * 4 // turns)[:, 0, :]
            np.testing.assert_array_equal(out[:, 3 * k : 3 * k + 3], want)
    with pytest.raises(ValueError, match="1, 2 or 4"):
        turned_embedder(first_point, 3)
