"""Shared by the models tests: small random clouds, models with non-trivial batch-norm
statistics, and the configurations under test."""

from __future__ import annotations

import torch

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model

SMALL = 256  # points per cloud in most tests


def clouds(b: int, n: int = SMALL, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 3, generator=g) * 2 - 1


def trained_like(cfg: ModelConfig, seed: int = 0) -> torch.nn.Module:
    """A model whose batch norms hold non-trivial statistics and affine parameters (so folding
    them is actually exercised), in eval mode."""
    torch.manual_seed(seed)
    model = build_model(cfg)
    model.train()
    with torch.no_grad():
        for i in range(3):
            model(clouds(4, seed=100 + i))
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.3, 0.3)
        # Transform nets start at the identity; move them so their weights matter.
        for name, p in model.named_parameters():
            if name.endswith("tnet.out.weight"):
                p.normal_(0, 0.01)
    return model.eval()


CONFIGS = {
    "compact": ModelConfig.compact(num_points=SMALL),
    "paper-narrow": ModelConfig.paper(
        num_points=SMALL,
        stem_widths=(16, 16),
        trunk_widths=(16, 32, 64),
        tnet_point_widths=(16, 32, 64),
        tnet_fc_widths=(32, 16),
        cluster_size=8,
        output_dim=32,
    ),
    "port-narrow": ModelConfig.port(
        num_points=SMALL, stem_widths=(16, 16), trunk_widths=(16, 32, 64), cluster_size=8
    ),
    # The port's affine last layer (no ReLU, no per-point norm) into NetVLAD without its
    # batch norms, and as the only trunk layer right after the feature transform.
    "port-affine-no-bn": ModelConfig.port(
        num_points=SMALL,
        trunk_widths=(16, 32),
        stem_widths=(8, 8),
        cluster_size=4,
        trunk_batch_norm=False,
        vlad_batch_norm=False,
    ),
    "port-affine-one-layer": ModelConfig.port(
        num_points=SMALL, trunk_widths=(24,), stem_widths=(8, 8), cluster_size=4
    ),
    "max": ModelConfig.compact(arch="pointnet-max", feature_transform=True),
    "max-no-bn": ModelConfig.compact(
        arch="pointnet-max", vlad_batch_norm=False, trunk_batch_norm=False, gating=False
    ),
    "vlad-no-bn-one-layer": ModelConfig.compact(
        vlad_batch_norm=False, trunk_widths=(48,), feature_transform=True, input_transform=False
    ),
}


#: A small bev-netvlad (a 32 x 32 image, three convolutions), for the tests of export and packaging.
BEV_SMALL = ModelConfig.bev(
    num_points=SMALL,
    bev_grid=32,
    bev_widths=(8, 8, 16),
    bev_strides=(2, 1, 2),
    bev_feature_dim=16,
    cluster_size=4,
    output_dim=16,
)
