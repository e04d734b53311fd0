"""The NetVLAD pooling head both encoders share, and its context gating.

:class:`~pnvlad_service.models.pointnetvlad.PointNetVLAD` pools its points with it (PN_VLAD),
:class:`~pnvlad_service.models.bev.BEVNetVLAD` the cells of its bird's-eye feature map; the fast
training path (:mod:`.training_path`) computes the same head from its parameters. Parameter
names (the layout ``model.safetensors`` stores, under the encoder's ``pool.``):
``cluster_weights`` [D, K], ``cluster_bn`` (or ``cluster_biases`` [K]), ``centers`` [D, K],
``fc.weight`` [out, D*K] over the residuals flattened feature-major (index d*K + k, as both
published codes), ``fc_bn`` (or ``fc.bias``), ``gating.gate.weight`` [out, out],
``gating.gate_bn`` (or ``gating.gate.bias``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


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
