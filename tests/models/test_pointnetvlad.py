"""models.pointnetvlad: the network's formulas, gradients, full size, and that it can learn."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import Encoder
from tests.models.helpers import CONFIGS, SMALL, clouds, trained_like


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_forward_shape_unit_norm_and_permutation_invariance(name: str) -> None:
    cfg = CONFIGS[name]
    model = trained_like(cfg)
    x = clouds(3)
    x[1, :, 2] *= 0.1  # a flat cloud: must get a clearly different descriptor
    with torch.no_grad():
        y = model(x)
        perm = torch.randperm(x.shape[1], generator=torch.Generator().manual_seed(1))
        y_perm = model(x[:, perm])
    assert y.shape == (3, cfg.output_dim) and y.dtype == torch.float32
    assert torch.allclose(y.norm(dim=1), torch.ones(3), atol=1e-6)
    assert (y - y_perm).abs().max() < 1e-5
    assert (y[0] - y[1]).abs().max() > 1e-3  # different clouds, different descriptors


def test_tf_variant_normalises_points_port_does_not() -> None:
    tf = trained_like(CONFIGS["paper-narrow"])
    port = trained_like(CONFIGS["port-narrow"])
    with torch.no_grad():
        f_tf = tf.point_features(clouds(2))
        f_port = port.point_features(clouds(2))
    assert torch.allclose(f_tf.norm(dim=2), torch.ones(2, SMALL), atol=1e-5)
    assert f_tf.min() >= 0  # ReLU after the last layer
    assert f_port.min() < 0  # no ReLU after the last layer (batch norm output)


def test_every_parameter_gets_a_gradient() -> None:
    cfg = ModelConfig.paper(
        num_points=64, stem_widths=(8, 8), trunk_widths=(8, 16), cluster_size=4, output_dim=8
    )
    model = build_model(cfg).train()
    # Transform nets start exactly at the identity (zero last layer), so nudge them first.
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("tnet.out.weight"):
                p.normal_(0, 0.01)
    y = model(clouds(6, n=64))
    (y[:3] - y[3:]).pow(2).sum().backward()
    # A bias right before a training-mode batch norm cancels in its mean: zero gradient, exactly.
    before_bn = {
        f"{net}.points.{i}.bias" for net in ("input_tnet", "feature_tnet") for i in range(3)
    }
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        if name in before_bn:
            w = model.get_parameter(name.replace(".bias", ".weight")).grad
            assert w is not None and p.grad.abs().max() < 1e-3 * w.abs().max(), name
        else:
            assert p.grad.abs().sum() > 0, name


def test_paper_config_full_size_forward() -> None:
    cfg = ModelConfig.paper()
    model = trained_like(cfg)
    x = clouds(2, n=4096, seed=5)
    with torch.no_grad():
        y = model(x)
    enc = Encoder(model, cfg)
    e = enc.embed(x.numpy())
    assert e.shape == (2, 256) and e.dtype == np.float32
    assert np.abs(e - y.numpy()).max() < 1e-5
    perm = torch.randperm(4096)
    assert np.abs(enc.embed(x[:, perm]) - e).max() < 1e-5


@pytest.mark.slow
def test_compact_config_learns_to_tell_places_apart() -> None:
    """60 Adam steps of the lazy quadruplet loss on 12 synthetic 'places' (the same four blobs,
    each place moving them a little; a new point sample and offset every time) lift top-1
    retrieval of fresh samples well above the untrained network's."""
    from pnvlad_service.training.losses import lazy_quadruplet_loss

    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    places, n = 12, 256
    common = torch.rand(4, 3, generator=g) * 1.6 - 0.8
    spread = torch.rand(4, 3, generator=g) * 0.3 + 0.1
    centres = [common + (torch.rand(4, 3, generator=g) - 0.5) * 0.25 for _ in range(places)]

    def sample(s: int, gen: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, 4, (n,), generator=gen)
        pts = centres[s][idx] + torch.randn(n, 3, generator=gen) * spread[idx]
        return (pts + 0.03 * torch.randn(1, 3, generator=gen)).clamp(-1, 1)

    cfg = ModelConfig.compact(num_points=n)
    model = build_model(cfg)

    def recall_at_1() -> float:
        ge = torch.Generator().manual_seed(123)
        db = torch.stack([sample(s, ge) for s in range(places)])
        q = torch.stack([sample(s, ge) for s in range(places)])
        enc = Encoder(model, cfg)
        d, e = enc.embed(db), enc.embed(q)
        nearest = ((e[:, None] - d[None]) ** 2).sum(-1).argmin(1)
        return float((nearest == np.arange(places)).mean())

    before = recall_at_1()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    for _ in range(60):
        tuples = []
        for s in torch.randint(0, places, (2,), generator=g).tolist():
            others = [o for o in range(places) if o != s]
            order = torch.randperm(len(others), generator=g).tolist()
            negs = [others[i] for i in order[:7]]
            tuples += [sample(s, g) for _ in range(3)] + [sample(m, g) for m in negs]
            tuples.append(sample(others[order[7]], g))
        d = model(torch.stack(tuples)).reshape(2, 11, -1)
        loss = lazy_quadruplet_loss(d[:, 0], d[:, 1:3], d[:, 3:10], d[:, 10])
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = recall_at_1()
    assert after >= 0.5 and after >= before + 0.25, (before, after)
