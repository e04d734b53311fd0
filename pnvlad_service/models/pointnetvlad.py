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
- PN_VLAD ``pool.*``: the NetVLAD head (:class:`~.netvlad.NetVLAD`, whose docstring lists its
  parameters).
- PN_MAX ``pool.fc`` Linear(D, out) and ``pool.gating.*`` as NetVLAD's.

The forward pass is :func:`fast_forward`, built from :mod:`.training_path`'s fused operations;
:meth:`PointNetVLAD.reference_forward` is the same computation layer by layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.heading import canonical_heading
from pnvlad_service.models.local_shape import split_inputs
from pnvlad_service.models.netvlad import ContextGating, NetVLAD
from pnvlad_service.models.training_path import (
    affine_netvlad_forward,
    folded_linear,
    lin_act,
    linear_bn_max,
    netvlad_forward,
    relu_l2_netvlad_forward,
)


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
        if self.cfg.canonical_heading:
            points = canonical_heading(points)
        if not self.fast_path:
            return self.reference_forward(points)
        return fast_forward(self, points)

    def reference_forward(self, points: torch.Tensor) -> torch.Tensor:
        """The forward pass layer by layer through the modules (what :meth:`forward` computes
        faster, :func:`fast_forward`; kept as its reference and for comparisons)."""
        return F.normalize(self.pool(self.point_features(points)), dim=1)


def _tnet(net: TransformNet, x: torch.Tensor) -> torch.Tensor:
    """The transform net's k x k matrix [B, k, k] of x [B, N, C] (reference
    ``TransformNet.forward``)."""
    b, n, c = x.shape
    h = x.reshape(b * n, c)
    last = len(net.points) - 1
    for lin, bn in zip(list(net.points)[:last], list(net.points_bn)[:last], strict=True):
        h = lin_act(lin, bn, h, True)
    g = linear_bn_max(net.points[last], net.points_bn[last], h.reshape(b, n, -1), relu=True)
    for lin, bn in zip(net.fcs, net.fcs_bn, strict=True):
        g = F.relu(bn(lin(g)))
    return (net.out(g) + net.identity).reshape(b, net.k, net.k)


def fast_forward(model: PointNetVLAD, points: torch.Tensor) -> torch.Tensor:
    """``model(points)`` computed the fast way: points [B, N, 3] -> [B, out], unit rows."""
    cfg = model.cfg
    xyz, shape = split_inputs(points, cfg.local_k)
    b, n, _ = xyz.shape
    h = xyz.reshape(b * n, 3)
    pending: torch.Tensor | None = None  # a transform to fold into the next per-point layer
    if model.input_tnet is not None:
        pending = _tnet(model.input_tnet, xyz)
    if shape is not None:  # the transform turns x, y, z only: apply it, then append the rest
        x = xyz if pending is None else torch.bmm(xyz, pending)
        h = torch.cat([x, shape], dim=2).reshape(b * n, -1)
        pending = None
    layers = [(lin, bn, True) for lin, bn in zip(model.stem, model.stem_bn, strict=True)]
    feat_at = len(layers)
    last = len(model.trunk) - 1
    layers += [
        (lin, bn, i < last or cfg.last_relu)
        for i, (lin, bn) in enumerate(zip(model.trunk, model.trunk_bn, strict=True))
    ]
    vlad = isinstance(model.pool, NetVLAD)
    # The paper's last layer: ReLU, per-point L2 and NetVLAD as one pair of autograd Functions.
    fused = vlad and layers[-1][2] and cfg.point_l2_norm and len(model.trunk) > 0
    for i, (lin, bn, relu) in enumerate(layers):
        if i == feat_at and model.feature_tnet is not None:
            if pending is not None:  # no stem layer took the input transform
                h = torch.bmm(h.reshape(b, n, -1), pending).reshape(b * n, -1)
            pending = _tnet(model.feature_tnet, h.reshape(b, n, -1))
        last = i == len(layers) - 1
        if last and vlad and not relu and not cfg.point_l2_norm:
            if pending is not None:
                h = torch.bmm(h.reshape(b, n, -1), pending).reshape(b * n, -1)
            assert isinstance(model.pool, NetVLAD)
            return F.normalize(affine_netvlad_forward(model.pool, lin, bn, h, b, n), dim=1)
        if last and not vlad:
            src = h if pending is None else torch.bmm(h.reshape(b, n, -1), pending)
            g = linear_bn_max(lin, bn, src.reshape(b, n, -1), relu)
            y = model.pool.fc(g)
            gating = model.pool.gating
            return F.normalize(gating(y) if gating is not None else y, dim=1)
        relu = relu and not (last and fused)  # the fused head applies it
        if pending is not None:
            z = bn(folded_linear(lin, pending, h, b, n))
            h = z.relu_() if relu else z
            pending = None
        else:
            h = lin_act(lin, bn, h, relu)
    if pending is not None:  # a transform after the last layer (not a shipped configuration)
        h = torch.bmm(h.reshape(b, n, -1), pending).reshape(b * n, -1)
    assert isinstance(model.pool, NetVLAD)
    if fused:
        return F.normalize(relu_l2_netvlad_forward(model.pool, h, b, n), dim=1)
    inv = None
    if cfg.point_l2_norm:
        inv = 1.0 / torch.linalg.vector_norm(h, dim=1, keepdim=True).clamp_min(1e-12)
    return F.normalize(netvlad_forward(model.pool, h, inv, b, n), dim=1)
