"""models.factory: one config, the encoder its ``arch`` names, fresh and ready to train."""

from __future__ import annotations

import pytest
import torch

from pnvlad_service.models.bev import BEVNetVLAD
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.netvlad import NetVLAD
from pnvlad_service.models.pointnetvlad import MaxPoolHead, PointNetVLAD


@pytest.mark.parametrize(
    ("cfg", "cls", "head"),
    [
        (ModelConfig.compact(), PointNetVLAD, NetVLAD),
        (ModelConfig.compact(arch="pointnet-max"), PointNetVLAD, MaxPoolHead),
        (ModelConfig.bev(), BEVNetVLAD, NetVLAD),
    ],
    ids=["pointnetvlad", "pointnet-max", "bev-netvlad"],
)
def test_build_model_follows_the_arch(cfg: ModelConfig, cls: type, head: type) -> None:
    model = build_model(cfg)
    assert type(model) is cls and type(model.pool) is head and model.cfg == cfg
    assert model.training
    assert {p.dtype for p in model.parameters()} == {torch.float32}
    assert {p.device.type for p in model.parameters()} == {"cpu"}
