"""PointNetVLAD (PN_VLAD) and PointNet-max (PN_MAX) as trainable ``torch.nn.Module``s.

Every per-point layer is a matrix product on the points x channels matrix [B*N, C] (what the
published code writes as a 1x1 convolution), so training and inference run as large GEMMs. Batch
norm layers are ``BatchNorm1d`` over the B*N rows, which is what a ``BatchNorm2d`` over
[B, C, N, 1] computes. For fast inference, fold the batch norms with
:class:`pnvlad_service.models.inference.Encoder`.

Parameter names (the layout ``model.safetensors`` stores):

- ``input_tnet.*`` / ``feature_tnet.*`` (:class:`TransformNet`): ``points.{i}`` Linear,
  ``points_bn.{i}``, ``fcs.{i}`` Linear, ``fcs_bn.{i}``, ``out`` Linear to k*k (identity added).
- ``stem.{i}`` / ``stem_bn.{i}`` and ``trunk.{i}`` / ``trunk_bn.{i}``: per-point Linear layers.
- PN_VLAD ``pool.*`` (:class:`NetVLAD`): ``cluster_weights`` [D, K], ``cluster_bn`` (or
  ``cluster_biases`` [K]), ``centers`` [D, K], ``fc.weight`` [out, D*K] over the residuals
  flattened feature-major (index d*K + k, as both published codes), ``fc_bn`` (or ``fc.bias``),
  ``gating.gate.weight`` [out, out], ``gating.gate_bn`` (or ``gating.gate.bias``).
- PN_MAX ``pool.fc`` Linear(D, out) and ``pool.gating.*`` as above.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.local_shape import split_inputs


class TransformNet(nn.Module):
    """PointNet's T-net: predicts a k x k matrix from a cloud's per-point features.

    ``forward(x float32 [B, N, C]) -> float32 [B, k, k]``; the points are then transformed as row
    vectors, ``x @ T`` (as both published codes). The last layer starts at zero, so T starts as
    the identity.
    """

    def __init__(
        self, c_in: int, k: int, point_widths: tuple[int, ...], fc_widths: tuple[int, ...], bn: bool
    ) -> None:
        super().__init__()
        self.k = k
        self.bn = bn
        self.points = nn.ModuleList()
        self.points_bn = nn.ModuleList()
        c = c_in
        for w in point_widths:
            self.points.append(nn.Linear(c, w))
            self.points_bn.append(nn.BatchNorm1d(w) if bn else nn.Identity())
            c = w
        self.fcs = nn.ModuleList()
        self.fcs_bn = nn.ModuleList()
        for w in fc_widths:
            self.fcs.append(nn.Linear(c, w))
            self.fcs_bn.append(nn.BatchNorm1d(w) if bn else nn.Identity())
            c = w
        self.out = nn.Linear(c, k * k)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self.register_buffer("identity", torch.eye(k).reshape(-1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        h = x.reshape(b * n, c)
        for lin, bn in zip(self.points, self.points_bn, strict=True):
            h = F.relu(bn(lin(h)))
        h = h.reshape(b, n, -1).amax(dim=1)
        for lin, bn in zip(self.fcs, self.fcs_bn, strict=True):
            h = F.relu(bn(lin(h)))
        t = self.out(h) + self.identity
        return t.reshape(b, self.k, self.k)


class ContextGating(nn.Module):
    """``x * sigmoid(BN(x @ W))`` (or ``x @ W + b`` without batch norm); x float32 [B, C]."""

    def __init__(self, dim: int, bn: bool) -> None:
        super().__init__()
        self.gate = nn.Linear(dim, dim, bias=not bn)
        nn.init.normal_(self.gate.weight, std=1.0 / math.sqrt(dim))
        if not bn:
            nn.init.normal_(self.gate.bias, std=1.0 / math.sqrt(dim))
        self.gate_bn = nn.BatchNorm1d(dim) if bn else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(self.gate_bn(self.gate(x)))


class NetVLAD(nn.Module):
    """NetVLAD pooling with K learned clusters, a fully connected layer and context gating.

    ``forward(x float32 [B, N, D]) -> float32 [B, out]`` (not yet L2-normalised):
    soft assignment ``a = softmax(BN(x @ cluster_weights))`` [B, N, K]; residual sums
    ``v[d, k] = sum_n a[n, k] * (x[n, d] - centers[d, k])``; intra-normalisation (L2 over d for
    every cluster k); L2 over the whole D*K vector (flattened d-major); ``fc``; batch norm;
    context gating.
    """

    def __init__(self, dim: int, clusters: int, out: int, bn: bool, gating: bool) -> None:
        super().__init__()
        self.dim, self.clusters, self.bn = dim, clusters, bn
        std = 1.0 / math.sqrt(dim)
        self.cluster_weights = nn.Parameter(torch.randn(dim, clusters) * std)
        if bn:
            self.cluster_bn = nn.BatchNorm1d(clusters)
        else:
            self.cluster_biases = nn.Parameter(torch.randn(clusters) * std)
        self.centers = nn.Parameter(torch.randn(dim, clusters) * std)
        self.fc = nn.Linear(dim * clusters, out, bias=not bn)
        nn.init.normal_(self.fc.weight, std=1.0 / math.sqrt(clusters))
        if not bn:
            nn.init.zeros_(self.fc.bias)
        self.fc_bn = nn.BatchNorm1d(out) if bn else nn.Identity()
        self.gating = ContextGating(out, bn) if gating else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        logits = x.reshape(b * n, d) @ self.cluster_weights
        logits = self.cluster_bn(logits) if self.bn else logits + self.cluster_biases
        a = torch.softmax(logits, dim=-1).reshape(b, n, self.clusters)
        # [b, K, N] x [b, N, D]: x is used as stored (no copy), the small result is transposed.
        vlad = torch.bmm(a.transpose(1, 2), x).transpose(1, 2)
        vlad = vlad - a.sum(dim=1, keepdim=True) * self.centers  # [b, D, K]
        vlad = F.normalize(vlad, dim=1)  # intra-normalisation
        vlad = F.normalize(vlad.reshape(b, d * self.clusters), dim=1)
        y = self.fc_bn(self.fc(vlad))
        return self.gating(y) if self.gating is not None else y


class MaxPoolHead(nn.Module):
    """PN_MAX head: max over points, a fully connected layer, optional context gating.

    ``forward(x float32 [B, N, D]) -> float32 [B, out]`` (not yet L2-normalised).
    """

    def __init__(self, dim: int, out: int, bn: bool, gating: bool) -> None:
        super().__init__()
        self.fc = nn.Linear(dim, out)
        self.gating = ContextGating(out, bn) if gating else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.fc(x.amax(dim=1))
        return self.gating(y) if self.gating is not None else y


class PointNetVLAD(nn.Module):
    """The encoder: a PointNet trunk and a NetVLAD (``pointnetvlad``) or max (``pointnet-max``)
    pooling head, then L2 normalisation.

    ``forward(points float32 [B, N, 3]) -> float32 [B, output_dim]``, each row of unit L2 norm
    (with ``cfg.local_k``, points [B, N, 10] that carry their shape features are taken too).
    N may differ from ``cfg.num_points``; the descriptor does not depend on the points' order.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        #: False: :meth:`forward` is :meth:`reference_forward` (for comparisons; same result).
        self.fast_path = True
        self.input_tnet = (
            TransformNet(3, 3, cfg.tnet_point_widths, cfg.tnet_fc_widths, cfg.tnet_batch_norm)
            if cfg.input_transform
            else None
        )
        self.stem, self.stem_bn = self._layers(cfg.input_dim, cfg.stem_widths)
        c = cfg.stem_widths[-1] if cfg.stem_widths else cfg.input_dim
        self.feature_tnet = (
            TransformNet(c, c, cfg.tnet_point_widths, cfg.tnet_fc_widths, cfg.tnet_batch_norm)
            if cfg.feature_transform
            else None
        )
        self.trunk, self.trunk_bn = self._layers(c, cfg.trunk_widths)
        d = cfg.feature_dim
        self.pool: nn.Module
        if cfg.arch == "pointnetvlad":
            self.pool = NetVLAD(
                d, cfg.cluster_size, cfg.output_dim, cfg.vlad_batch_norm, cfg.gating
            )
        else:
            self.pool = MaxPoolHead(d, cfg.output_dim, cfg.vlad_batch_norm, cfg.gating)

    def _layers(self, c: int, widths: tuple[int, ...]) -> tuple[nn.ModuleList, nn.ModuleList]:
        lins, bns = nn.ModuleList(), nn.ModuleList()
        for w in widths:
            lins.append(nn.Linear(c, w))
            bns.append(nn.BatchNorm1d(w) if self.cfg.trunk_batch_norm else nn.Identity())
            c = w
        return lins, bns

    def point_features(self, points: torch.Tensor) -> torch.Tensor:
        """Per-point features float32 [B, N, D] of points float32 [B, N, 3] (before pooling,
        after the per-point L2 normalisation when ``cfg.point_l2_norm`` and the head is NetVLAD).
        With ``cfg.local_k`` the points may carry their shape features already ([B, N, 10],
        ``local_shape.split_inputs``)."""
        x, shape = split_inputs(points, self.cfg.local_k)
        b, n, _ = x.shape
        if self.input_tnet is not None:
            x = x @ self.input_tnet(x)
        if shape is not None:
            x = torch.cat([x, shape], dim=2)
        h = x.reshape(b * n, -1)
        for lin, bn in zip(self.stem, self.stem_bn, strict=True):
            h = F.relu(bn(lin(h)))
        if self.feature_tnet is not None:
            hb = h.reshape(b, n, -1)
            h = (hb @ self.feature_tnet(hb)).reshape(b * n, -1)
        last = len(self.trunk) - 1
        for i, (lin, bn) in enumerate(zip(self.trunk, self.trunk_bn, strict=True)):
            h = bn(lin(h))
            if i < last or self.cfg.last_relu:
                h = F.relu(h)
        if self.cfg.point_l2_norm and self.cfg.arch == "pointnetvlad":
            h = F.normalize(h, dim=1)
        return h.reshape(b, n, -1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if not self.fast_path:
            return self.reference_forward(points)
        from pnvlad_service.models.training_path import fast_forward

        return fast_forward(self, points)

    def reference_forward(self, points: torch.Tensor) -> torch.Tensor:
        """The forward pass layer by layer through the modules (what :meth:`forward` computes
        faster, see ``training_path.py``; kept as its reference and for comparisons)."""
        return F.normalize(self.pool(self.point_features(points)), dim=1)


def build_model(cfg: ModelConfig) -> nn.Module:
    """A freshly initialised encoder for ``cfg`` (in training mode, float32, on the CPU): a
    :class:`PointNetVLAD`, or for ``arch`` 'bev-netvlad' a :class:`.bev.BEVNetVLAD`."""
    if cfg.arch == "bev-netvlad":
        from pnvlad_service.models.bev import BEVNetVLAD

        return BEVNetVLAD(cfg)
    return PointNetVLAD(cfg)
