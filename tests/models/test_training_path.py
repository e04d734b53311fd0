"""The fast forward pass (``pointnetvlad.fast_forward`` and the fused operations of
models/training_path.py) against the modules' own layer-by-layer forward
(``PointNetVLAD.reference_forward``, the implementation before it): same weights and inputs give
the same descriptors, the same gradients of every parameter and the same batch-norm running
statistics, in training and in eval mode."""

from __future__ import annotations

import copy

import pytest
import torch

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.training_path import BatchStats, LinearMax
from tests.models.helpers import CONFIGS, clouds, trained_like

CASES = {
    **CONFIGS,
    "paper-max-narrow": CONFIGS["paper-narrow"].model_copy(update={"arch": "pointnet-max"}),
    "port-max-last-no-relu": ModelConfig.port(
        num_points=64, arch="pointnet-max", trunk_widths=(16, 32), stem_widths=(8, 8)
    ),
}


def _pair(cfg: ModelConfig, train: bool) -> tuple[torch.nn.Module, torch.nn.Module]:
    fast = trained_like(cfg).double().train(train)
    ref = copy.deepcopy(fast)
    ref.fast_path = False
    return fast, ref


@pytest.mark.parametrize("train", [True, False], ids=["train", "eval"])
@pytest.mark.parametrize("name", list(CASES))
def test_fast_path_matches_reference(name: str, train: bool) -> None:
    fast, ref = _pair(CASES[name], train)
    x = clouds(3, n=96, seed=5).double()
    y_fast, y_ref = fast(x), ref(x)
    torch.testing.assert_close(y_fast, y_ref, rtol=1e-9, atol=1e-11)
    w = torch.randn(y_ref.shape, generator=torch.Generator().manual_seed(1), dtype=x.dtype)
    (y_fast * w).sum().backward()
    (y_ref * w).sum().backward()
    top = max(q.grad.abs().max().item() for q in ref.parameters() if q.grad is not None)
    for (pname, p), q in zip(fast.named_parameters(), ref.parameters(), strict=True):
        assert p.grad is not None and q.grad is not None, pname
        # Biases right before a training-mode batch norm: exactly 0 against rounding noise.
        scale = max(q.grad.abs().max().item(), 1e-4 * top)
        assert (p.grad - q.grad).abs().max().item() <= 1e-7 * scale, pname
    for (bname, a), b in zip(fast.named_buffers(), ref.buffers(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12, msg=bname)


def test_float32_full_width_paper_is_as_accurate_as_the_reference() -> None:
    """The shipped paper configuration in float32 (the training dtype) on 3 clouds: the fast
    path's descriptors and gradients are as close to a float64 reference as the float32
    reference itself is, or within 1 % (batch norm over 3 rows in the head is ill-conditioned,
    so a float32 error is real for both)."""
    cfg = ModelConfig.paper(num_points=512)
    torch.manual_seed(0)
    fast = build_model(cfg).train()
    with torch.no_grad():
        for name, p in fast.named_parameters():
            if name.endswith("tnet.out.weight"):
                p.normal_(0, 0.01)
    ref = copy.deepcopy(fast)
    ref.fast_path = False
    exact = copy.deepcopy(ref).double()
    x = clouds(3, n=512, seed=3)
    ys = [
        m(x.to(dt))
        for m, dt in ((fast, torch.float32), (ref, torch.float32), (exact, torch.float64))
    ]
    for y in ys:
        (y[0] - y[1]).pow(2).sum().backward()
    err_fast = (ys[0].double() - ys[2]).abs().max().item()
    err_ref = (ys[1].double() - ys[2]).abs().max().item()
    assert err_fast <= 3 * err_ref + 1e-6, (err_fast, err_ref)
    top = max(e.grad.abs().max().item() for e in exact.parameters() if e.grad is not None)
    named = zip(fast.named_parameters(), ref.parameters(), exact.parameters(), strict=True)
    for (pname, p), q, e in named:
        assert p.grad is not None and q.grad is not None and e.grad is not None, pname
        gf = (p.grad.double() - e.grad).abs().max().item()
        gr = (q.grad.double() - e.grad).abs().max().item()
        # Within 3x the reference's own float32 error, or 1 % of the gradient's size (the
        # covariance-based batch statistics round differently from the direct ones).
        # (Biases before a batch norm: exactly 0, so noise against noise, on the model's scale.)
        tol = max(3 * gr, 1e-2 * e.grad.abs().max().item(), 1e-5 * top)
        assert gf <= tol, (pname, gf, gr)


@pytest.mark.parametrize("relu", [True, False])
def test_linear_max_gradcheck(relu: bool) -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 7, 4, dtype=torch.float64, generator=g, requires_grad=True)
    w = torch.randn(4, 5, dtype=torch.float64, generator=g, requires_grad=True)
    t = torch.randn(5, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, w, t: LinearMax.apply(x, w, t, relu), (x, w, t))
    want = (x @ w + t).amax(1)
    want = want.relu() if relu else want
    torch.testing.assert_close(LinearMax.apply(x, w, t, relu), want)


@pytest.mark.parametrize("block", [4096, 5])
def test_batch_stats_gradcheck_and_values(block: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """BatchStats' mean and variance are those of the [M, O] product it never forms, and its
    written-out backward is autograd's (float64 gradcheck; blocks of 5 rows of 13 too)."""
    monkeypatch.setattr(BatchStats, "BLOCK", block)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(13, 4, dtype=torch.float64, generator=g, requires_grad=True)
    w = torch.randn(4, 6, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.randn(6, dtype=torch.float64, generator=g, requires_grad=True)
    mean, var = BatchStats.apply(x, w, b)
    y = x @ w + b
    torch.testing.assert_close(mean, y.mean(0))
    torch.testing.assert_close(var, y.var(0, unbiased=False))
    assert torch.autograd.gradcheck(lambda x, w, b: BatchStats.apply(x, w, b), (x, w, b))


@pytest.mark.parametrize("bn", [True, False])
def test_fused_relu_l2_netvlad_gradcheck(bn: bool) -> None:
    """The pair of Functions that computes ReLU, the per-point L2 norm and NetVLAD's sums (and
    forms their gradient in one product a cloud) against autograd, in float64, 2 clouds."""
    from pnvlad_service.models.netvlad import NetVLAD
    from pnvlad_service.models.training_path import relu_l2_netvlad_forward

    torch.manual_seed(0)
    pool = NetVLAD(5, 3, 4, bn=bn, gating=True).double().train()
    z = torch.randn(2 * 6, 5, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        z[3] = -1.0  # a point whose features are all zero after the ReLU (norm clamped)

    def fused(z: torch.Tensor) -> torch.Tensor:
        return relu_l2_netvlad_forward(pool, z, 2, 6)

    def reference(z: torch.Tensor) -> torch.Tensor:
        h = torch.nn.functional.normalize(torch.relu(z), dim=1)
        return pool(h.reshape(2, 6, 5))

    torch.testing.assert_close(fused(z), reference(z))
    assert torch.autograd.gradcheck(fused, (z,))


def test_the_paper_head_takes_the_fused_functions(monkeypatch: pytest.MonkeyPatch) -> None:
    from pnvlad_service.models import training_path

    calls = []
    real = training_path._VladIn.forward
    monkeypatch.setattr(
        training_path._VladIn, "forward", staticmethod(lambda *a: calls.append(1) or real(*a))
    )
    for name in ("compact", "paper-narrow"):
        model = trained_like(CONFIGS[name]).train()
        calls.clear()
        model(clouds(2, n=64))
        assert len(calls) == 1, name


def test_state_dict_unchanged_by_the_fast_path() -> None:
    cfg = CONFIGS["compact"]
    fast = build_model(cfg)
    ref = build_model(cfg)
    ref.fast_path = False
    assert list(fast.state_dict()) == list(ref.state_dict())
    ref.load_state_dict(fast.state_dict())
    x = clouds(2)
    torch.testing.assert_close(fast.eval()(x), ref.eval()(x), rtol=1e-5, atol=1e-6)


def test_the_fused_head_trains_under_bfloat16_autocast() -> None:
    """The trainer's ``train.amp: bf16``: the fused Functions take bfloat16 features and give
    every parameter a finite float32 gradient, NetVLAD's about as far from the float32 one as
    the reference's under the same autocast (on this narrow random model bfloat16 moves both by
    tens of per cent)."""
    cfg = CONFIGS["paper-narrow"]
    base = trained_like(cfg).train()
    x = clouds(3, n=128, seed=2)
    w = torch.randn(3, cfg.output_dim, generator=torch.Generator().manual_seed(4))

    def grads(fast: bool, amp: bool) -> dict[str, torch.Tensor]:
        m = copy.deepcopy(base)
        m.fast_path = fast
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            y = m(x)
        (y.float() * w).sum().backward()
        return {n: p.grad for n, p in m.named_parameters() if p.grad is not None}

    exact, ref, fast = grads(False, False), grads(False, True), grads(True, True)
    assert set(fast) == set(exact)
    for name, g in fast.items():
        assert g.dtype == torch.float32 and torch.isfinite(g).all(), name
    name = "pool.cluster_weights"
    err_ref = (ref[name] - exact[name]).norm() / exact[name].norm()
    err_fast = (fast[name] - exact[name]).norm() / exact[name].norm()
    assert err_fast <= 2 * err_ref + 0.05, (err_fast, err_ref)
