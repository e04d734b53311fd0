"""The one place an encoder is built from its config: ``build_model(cfg)`` for every ``arch``."""

from __future__ import annotations

from torch import nn

from pnvlad_service.models.bev import BEVNetVLAD
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.pointnetvlad import PointNetVLAD


def build_model(cfg: ModelConfig) -> nn.Module:
    """A freshly initialised encoder for ``cfg`` (in training mode, float32, on the CPU): a
    :class:`~.pointnetvlad.PointNetVLAD` (``pointnetvlad``, ``pointnet-max``), or a
    :class:`~.bev.BEVNetVLAD` (``bev-netvlad``)."""
    if cfg.arch == "bev-netvlad":
        return BEVNetVLAD(cfg)
    return PointNetVLAD(cfg)
