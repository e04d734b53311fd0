"""models.config: the shipped configurations, FLOPs by hand, validation and the config hash."""

from __future__ import annotations

import hashlib
import json

import pytest

from pnvlad_service.models.config import BEV_FIELDS, ModelConfig
from pnvlad_service.models.store import (
    config_sha256,
)


def test_paper_config_is_the_published_network() -> None:
    cfg = ModelConfig.paper()
    assert cfg.arch == "pointnetvlad" and cfg.num_points == 4096
    assert cfg.stem_widths + cfg.trunk_widths == (64, 64, 64, 128, 1024)
    assert cfg.input_transform and cfg.feature_transform
    assert (cfg.cluster_size, cfg.output_dim, cfg.gating) == (64, 256, True)
    # The TensorFlow code's choices (docs/MODEL.md); the port flips all four.
    tf = (cfg.trunk_batch_norm, cfg.tnet_batch_norm, cfg.last_relu, cfg.point_l2_norm)
    assert tf == (False, True, True, True)
    port = ModelConfig.port()
    assert (port.trunk_batch_norm, port.tnet_batch_norm, port.last_relu, port.point_l2_norm) == (
        True,
        False,
        False,
        False,
    )


def test_flops_hand_count() -> None:
    cfg = ModelConfig(
        num_points=10,
        stem_widths=(4,),
        trunk_widths=(8,),
        input_transform=False,
        feature_transform=False,
        cluster_size=2,
        output_dim=3,
        gating=False,
    )
    # 10 points: 3->4 and 4->8 per point; logits 8->2 and sums 2x8 per point; fc 16->3.
    want = 2 * (10 * 3 * 4 + 10 * 4 * 8 + 10 * 8 * 2 + 10 * 2 * 8 + 16 * 3)
    assert cfg.flops_per_cloud() == want
    paper, compact = ModelConfig.paper().flops_per_cloud(), ModelConfig.compact().flops_per_cloud()
    assert 4.5e9 < paper < 4.8e9
    assert 8 < paper / compact < 12  # the compact configuration is about 10x cheaper


def test_config_validation_and_hash() -> None:
    with pytest.raises(ValueError, match="positive"):
        ModelConfig(trunk_widths=(64, 0))
    with pytest.raises(ValueError, match="extra"):
        ModelConfig(widths=(1, 2))  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="feature_transform"):
        ModelConfig(stem_widths=())
    a, b = ModelConfig.paper(), ModelConfig.paper(cluster_size=32)
    assert config_sha256(a) == config_sha256(ModelConfig.model_validate(a.model_dump(mode="json")))
    assert config_sha256(a) != config_sha256(b)
    # Fields newer than the first models are left out: local_k at 0, embed_scales empty, the
    # bev_* fields of a PointNet model (so the hash of a model saved before them does not change).
    skip = {"local_k", "canonical_heading", "embed_scales", *BEV_FIELDS}
    doc = {k: v for k, v in a.model_dump(mode="json").items() if k not in skip}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    assert config_sha256(a) == hashlib.sha256(text.encode()).hexdigest()
