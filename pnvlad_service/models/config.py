"""``ModelConfig``: every size and switch of the encoders (PointNetVLAD, PointNet-max and the
bird's-eye-view bev-netvlad).

Three configurations ship:

- :meth:`ModelConfig.paper` - the network of the paper, as the published TensorFlow code builds it
  (input transform 3x3, per-point layers 64, 64, feature transform 64x64, 64, 128, 1024; NetVLAD
  with K = 64 clusters; fully connected to 256; context gating; L2 normalisation).
- :meth:`ModelConfig.compact` - the same design, narrower, without the feature transform and with
  K = 16: about 10x cheaper, so it trains on a CPU.
- :meth:`ModelConfig.bev` - not the paper's network: the points counted into a bird's-eye image,
  a small 2-D CNN and the same NetVLAD head (models/bev.py); the best retrieval measured on a CPU
  budget (docs/TRAINING.md).

:meth:`ModelConfig.port` is the variant that the popular PyTorch port
(cattaneod/PointNetVlad-Pytorch)
builds; weights imported from it (``pnvlad model import``) run under that configuration. The
switches where the TensorFlow code and the port differ are documented in docs/MODEL.md.

This module imports only pydantic, so the CLI can read configurations without loading torch.
"""

from __future__ import annotations

import hashlib
import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Arch = Literal["pointnetvlad", "pointnet-max", "bev-netvlad"]


class ModelConfig(BaseModel):
    """Sizes and switches of an encoder; ``build_model(cfg)`` turns it into a ``torch.nn.Module``.

    Input: float32 points [B, N, 3] (a submap scaled into [-1, 1]; with ``local_k`` they may
    carry their shape features, [B, N, 10]); output float32
    [B, output_dim], every row of unit L2 norm.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    arch: Arch = Field(
        "pointnetvlad",
        description="'pointnetvlad' (PN_VLAD), 'pointnet-max' (PN_MAX), or 'bev-netvlad' (a "
        "bird's-eye-view image of the points, a 2-D CNN and the same NetVLAD head: models/bev.py).",
    )
    num_points: int = Field(4096, ge=1, description="Points per cloud the model is trained on.")

    local_k: int = Field(
        0,
        ge=0,
        description="Append local shape features of each point's k nearest neighbours to its "
        "coordinates (models/local_shape.py, after LPD-Net); 0: coordinates only, as the paper.",
    )
    canonical_heading: bool = Field(
        False,
        description="Turn each cloud so that its dominant direction lies along x before the "
        "network (models/heading.py): for single scans, whose heading on the map is unknown; "
        "trained with train.augment.quarter_turns.",
    )
    embed_scales: tuple[float, ...] = Field(
        (),
        description="Scales each cloud is embedded at, its descriptors averaged (the map's and "
        "the queries' alike; training sees one scale): filter G draws one place at sizes that "
        "differ between drives. Empty: the cloud as given.",
    )

    # Per-point trunk: shared layers (1x1 convolutions, i.e. matrix products over points).
    stem_widths: tuple[int, ...] = Field(
        (64, 64), description="Per-point layer widths before the feature transform."
    )
    trunk_widths: tuple[int, ...] = Field(
        (64, 128, 1024), description="Per-point layer widths after the feature transform."
    )
    input_transform: bool = Field(True, description="Learn a 3x3 transform of the input points.")
    feature_transform: bool = Field(
        True, description="Learn a CxC transform of the stem's features (C = stem_widths[-1])."
    )
    tnet_point_widths: tuple[int, ...] = Field(
        (64, 128, 1024), description="Per-point layer widths inside each transform net."
    )
    tnet_fc_widths: tuple[int, ...] = Field(
        (512, 256), description="Fully connected widths inside each transform net (after max-pool)."
    )

    # NetVLAD head.
    cluster_size: int = Field(64, ge=1, description="K, the number of learned NetVLAD clusters.")
    output_dim: int = Field(256, ge=1, description="Descriptor size.")
    gating: bool = Field(True, description="Context gating after the fully connected layer.")
    vlad_batch_norm: bool = Field(
        True,
        description="Batch norm on the cluster logits, after the fully connected layer and in the "
        "gating (as both published codes); False uses biases instead.",
    )

    # Where the TensorFlow code (True/False as noted) and the PyTorch port differ.
    trunk_batch_norm: bool = Field(
        False, description="Batch norm after each per-point trunk layer (TF: no; port: yes)."
    )
    tnet_batch_norm: bool = Field(
        True, description="Batch norm inside the transform nets (TF: yes; port: no)."
    )
    last_relu: bool = Field(
        True, description="ReLU after the last trunk layer (TF: yes; port: no)."
    )
    point_l2_norm: bool = Field(
        True,
        description="L2-normalise each point's feature before NetVLAD (TF: yes; port: no); "
        "PN_MAX ignores it.",
    )

    # Bird's-eye view (arch 'bev-netvlad' only; models/bev.py).
    bev_grid: int = Field(
        128, ge=4, description="Cells a side of the bird's-eye image over x, y in [-1, 1]."
    )
    bev_height_bins: int = Field(
        8, ge=1, description="Height slices: the image's channels (a count of points each)."
    )
    bev_z_range: tuple[float, float] = Field(
        (-0.04, 0.05),
        description="z (normalised units) the height slices span; points outside go to the "
        "first or last slice. The benchmark's submaps: 70 m a unit, so about 6 m of height.",
    )
    bev_widths: tuple[int, ...] = Field(
        (32, 32, 64, 64, 128, 128), description="Channels of the 3x3 convolutions."
    )
    bev_strides: tuple[int, ...] = Field(
        (2, 1, 2, 1, 2, 1), description="Stride of each 3x3 convolution (1 or 2)."
    )
    bev_feature_dim: int = Field(
        256, ge=1, description="D: channels of the 1x1 convolution whose cells NetVLAD pools."
    )

    @field_validator(
        "stem_widths", "trunk_widths", "tnet_point_widths", "tnet_fc_widths", "bev_widths"
    )
    @classmethod
    def _positive_widths(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if any(w < 1 for w in v):
            raise ValueError(f"widths must be positive, got {v}")
        return tuple(v)

    @model_validator(mode="after")
    def _check(self) -> ModelConfig:
        if not self.trunk_widths:
            raise ValueError("trunk_widths must name at least one layer")
        if self.feature_transform and not self.stem_widths:
            raise ValueError("feature_transform needs at least one stem layer to transform")
        if (self.input_transform or self.feature_transform) and not self.tnet_point_widths:
            raise ValueError("transform nets need at least one per-point layer")
        if 0 < self.local_k < 3:
            raise ValueError(f"local_k must be 0 or at least 3 (a covariance), got {self.local_k}")
        if len(self.embed_scales) > 8 or not all(0.25 <= f <= 4 for f in self.embed_scales):
            raise ValueError(f"embed_scales: at most 8, each in [0.25, 4], got {self.embed_scales}")
        if self.embed_scales and self.local_k:
            raise ValueError("embed_scales cannot rescale local shape features (local_k > 0)")
        if self.arch == "bev-netvlad":
            self._check_bev()
        return self

    def _check_bev(self) -> None:
        if self.local_k:
            raise ValueError("local_k applies to the PointNet architectures, not bev-netvlad")
        if not self.bev_widths or len(self.bev_strides) != len(self.bev_widths):
            raise ValueError(
                "bev_strides must give one stride per bev_widths layer, got "
                f"{len(self.bev_strides)} for {len(self.bev_widths)}"
            )
        if any(s not in (1, 2) for s in self.bev_strides):
            raise ValueError(f"bev_strides must be 1 or 2, got {self.bev_strides}")
        lo, hi = self.bev_z_range
        if not lo < hi:
            raise ValueError(f"bev_z_range must be (low, high) with low < high, got {lo}, {hi}")

    @property
    def bev_cells(self) -> int:
        """Cells a side of the feature map NetVLAD pools (``bev_grid`` after the strides)."""
        cells = self.bev_grid
        for s in self.bev_strides:
            cells = (cells - 1) // s + 1
        return cells

    @property
    def input_dim(self) -> int:
        """Channels a point enters the per-point layers with: x, y, z and, with ``local_k``,
        its local shape features."""
        if not self.local_k:
            return 3
        from pnvlad_service.models.local_shape import NUM_FEATURES

        return 3 + NUM_FEATURES

    @property
    def feature_dim(self) -> int:
        """D: the per-point (bev-netvlad: per-cell) feature size the pooling sees (the last
        trunk width, or ``bev_feature_dim``)."""
        return self.bev_feature_dim if self.arch == "bev-netvlad" else self.trunk_widths[-1]

    @classmethod
    def paper(cls, **overrides: object) -> ModelConfig:
        """PN_VLAD as published (TensorFlow code): about 4.4 GFLOP per 4096-point cloud."""
        return cls(**overrides)  # type: ignore[arg-type]

    @classmethod
    def port(cls, **overrides: object) -> ModelConfig:
        """PN_VLAD as the PyTorch port builds it (``PointNetVlad(..., feature_transform=True,
        max_pool=False, output_dim=256)``): batch norm in the trunk, none in the transform nets,
        no ReLU after the last trunk layer, no per-point normalisation."""
        base = {
            "trunk_batch_norm": True,
            "tnet_batch_norm": False,
            "last_relu": False,
            "point_l2_norm": False,
        }
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]

    @classmethod
    def compact(cls, **overrides: object) -> ModelConfig:
        """A CPU-trainable PN_VLAD: trunk 32, 32, 64, 128, 256; no feature transform; a narrow
        input transform net; K = 16; output 256. About 10x cheaper than :meth:`paper`."""
        base: dict[str, object] = {
            "stem_widths": (32, 32),
            "trunk_widths": (64, 128, 256),
            "feature_transform": False,
            "tnet_point_widths": (32, 64, 128),
            "tnet_fc_widths": (64, 32),
            "cluster_size": 16,
            "trunk_batch_norm": True,
        }
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]

    @classmethod
    def bev(cls, **overrides: object) -> ModelConfig:
        """bev-netvlad (models/bev.py): the points counted into a 128 x 128 x 8 bird's-eye image,
        six 3x3 convolutions (32, 32, 64, 64, 128, 128 channels, the first, third and fifth of
        stride 2), a 1x1 to 256, NetVLAD with K = 16 over the 16 x 16 cells, output 256. About
        0.34 GFLOP a cloud, for any number of points (docs/results/training.md, run 29)."""
        base: dict[str, object] = {"arch": "bev-netvlad", "cluster_size": 16}
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]

    def flops_per_cloud(self, num_points: int | None = None) -> int:
        """Multiply-adds x 2 of one forward pass on one cloud of ``num_points`` points.

        Counts the matrix products only (per-point layers, transform nets, NetVLAD's two products,
        the fully connected layer and the gating); element-wise work is ignored.
        """
        if self.arch == "bev-netvlad":
            return self._bev_flops()
        n = self.num_points if num_points is None else num_points
        flops = 0

        def tnet(c_in: int, k: int) -> int:
            f, c = 0, c_in
            for w in self.tnet_point_widths:
                f += 2 * n * c * w
                c = w
            for w in self.tnet_fc_widths:
                f += 2 * c * w
                c = w
            return f + 2 * c * k * k

        if self.input_transform:
            flops += tnet(3, 3) + 2 * n * 3 * 3
        c = self.input_dim
        for w in self.stem_widths:
            flops += 2 * n * c * w
            c = w
        if self.feature_transform:
            flops += tnet(c, c) + 2 * n * c * c
        for w in self.trunk_widths:
            flops += 2 * n * c * w
            c = w
        d = c
        if self.arch == "pointnetvlad":
            k = self.cluster_size
            flops += 2 * n * d * k  # soft-assignment logits
            flops += 2 * n * d * k  # weighted sums of the features
            flops += 2 * k * d * self.output_dim
        else:
            flops += 2 * d * self.output_dim
        if self.gating:
            flops += 2 * self.output_dim * self.output_dim
        return flops

    def _bev_flops(self) -> int:
        """The convolutions, the 1x1 convolution and the head of bev-netvlad (the image does
        not depend on the number of points; rasterising them is not counted)."""
        flops, c, cells = 0, self.bev_height_bins, self.bev_grid
        for w, s in zip(self.bev_widths, self.bev_strides, strict=True):
            cells = (cells - 1) // s + 1
            flops += 2 * cells * cells * c * w * 9
            c = w
        m, d, k = cells * cells, self.bev_feature_dim, self.cluster_size
        flops += 2 * m * c * d  # the 1x1 convolution
        flops += 2 * 2 * m * d * k  # NetVLAD's soft-assignment logits and weighted sums
        flops += 2 * k * d * self.output_dim
        if self.gating:
            flops += 2 * self.output_dim * self.output_dim
        return flops


#: The ``bev_*`` fields: left out of :func:`config_sha256` for the PointNet architectures, whose
#: models existed before them.
BEV_FIELDS = tuple(name for name in ModelConfig.model_fields if name.startswith("bev_"))


#: Headings a map entry is embedded at for a model that turns clouds to their own dominant
#: direction: that direction is known modulo a quarter turn.
QUARTER_TURNS = 4


def map_turns(cfg: ModelConfig | dict) -> int:
    """How many headings a map is embedded at for this model: :data:`QUARTER_TURNS` when it
    turns each cloud to its dominant direction (``canonical_heading``), else 1."""
    heading = cfg.get("canonical_heading") if isinstance(cfg, dict) else cfg.canonical_heading
    return QUARTER_TURNS if heading else 1


def config_sha256(cfg: ModelConfig) -> str:
    """SHA-256 (hex) of the configuration's canonical JSON (sorted keys, no spaces). Fields
    added since the first release are left out at their neutral value (``local_k`` 0,
    ``canonical_heading`` false, ``embed_scales`` empty, the
    ``bev_*`` fields of a PointNet model), so a model's hash does not change with the release
    that reads it."""
    doc = cfg.model_dump(mode="json")
    for name in ("local_k", "canonical_heading", "embed_scales"):
        if not doc[name]:
            del doc[name]
    if cfg.arch != "bev-netvlad":
        for name in BEV_FIELDS:
            del doc[name]
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
