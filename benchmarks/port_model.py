"""The PyTorch port's PN_VLAD, rebuilt for speed comparisons (not used by the package).

Written from the port's documented design (cattaneod/PointNetVlad-Pytorch,
``PointNetVlad(num_points=4096, global_feat=True, feature_transform=True, max_pool=False,
output_dim=256)``), with its parameter names, so a state dict of this module imports with
``pnvlad_service.models.port.convert_port_state`` and runs under ``ModelConfig.port()``. It
computes the way the port does: clouds as images [B, 1, N, 3] through ``Conv2d`` layers and
``BatchNorm2d``, max pooling with ``MaxPool2d``, the transform nets without batch norm, and
NetVLAD as ``matmul`` of the [B, N, D] features, ``a_sum * cluster_weights2`` broadcast and two
``F.normalize``. No code of the port is copied; the layout is what it runs, for a fair timing.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


class PortSTN(nn.Module):
    """Transform net of the port (``use_bn=False``): convs 64, 128, 1024, max pool, fc 512,
    256, k*k; the identity added."""

    def __init__(self, num_points: int, k: int) -> None:
        super().__init__()
        self.k = k
        kw = 3 if k == 3 else 1
        cin = 1 if k == 3 else k
        self.conv1 = nn.Conv2d(cin, 64, (1, kw))
        self.conv2 = nn.Conv2d(64, 128, (1, 1))
        self.conv3 = nn.Conv2d(128, 1024, (1, 1))
        self.mp1 = nn.MaxPool2d((num_points, 1), 1)
        self.fc1 = nn.Linear(1024, 512)
        self.fc2 = nn.Linear(512, 256)
        self.fc3 = nn.Linear(256, k * k)
        nn.init.zeros_(self.fc3.weight)
        nn.init.zeros_(self.fc3.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = x.shape[0]
        x = F.relu(self.conv1(x))
        x = F.relu(self.conv2(x))
        x = F.relu(self.conv3(x))
        x = self.mp1(x).view(b, -1)
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        x = self.fc3(x)
        eye = torch.eye(self.k, device=x.device, dtype=x.dtype).reshape(1, -1)
        return (x + eye).view(b, self.k, self.k)


class PortPointNet(nn.Module):
    def __init__(self, num_points: int) -> None:
        super().__init__()
        self.num_points = num_points
        self.stn = PortSTN(num_points, 3)
        self.feature_trans = PortSTN(num_points, 64)
        self.conv1 = nn.Conv2d(1, 64, (1, 3))
        self.conv2 = nn.Conv2d(64, 64, (1, 1))
        self.conv3 = nn.Conv2d(64, 64, (1, 1))
        self.conv4 = nn.Conv2d(64, 128, (1, 1))
        self.conv5 = nn.Conv2d(128, 1024, (1, 1))
        self.bn1 = nn.BatchNorm2d(64)
        self.bn2 = nn.BatchNorm2d(64)
        self.bn3 = nn.BatchNorm2d(64)
        self.bn4 = nn.BatchNorm2d(128)
        self.bn5 = nn.BatchNorm2d(1024)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x [B, 1, N, 3]
        t = self.stn(x)
        x = torch.matmul(x.squeeze(1), t).unsqueeze(1)
        x = F.relu(self.bn1(self.conv1(x)))
        x = F.relu(self.bn2(self.conv2(x)))  # [B, 64, N, 1]
        t = self.feature_trans(x)
        x = x.squeeze(-1).transpose(2, 1)
        x = torch.bmm(x, t).transpose(2, 1).contiguous().unsqueeze(-1)
        x = F.relu(self.bn3(self.conv3(x)))
        x = F.relu(self.bn4(self.conv4(x)))
        return self.bn5(self.conv5(x))  # [B, 1024, N, 1], no ReLU (the port's choice)


class PortGating(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gating_weights = nn.Parameter(torch.randn(dim, dim) / math.sqrt(dim))
        self.bn1 = nn.BatchNorm1d(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(self.bn1(torch.matmul(x, self.gating_weights)))


class PortNetVLAD(nn.Module):
    def __init__(self, d: int = 1024, k: int = 64, out: int = 256) -> None:
        super().__init__()
        self.d, self.k = d, k
        self.cluster_weights = nn.Parameter(torch.randn(d, k) / math.sqrt(d))
        self.cluster_weights2 = nn.Parameter(torch.randn(1, d, k) / math.sqrt(d))
        self.hidden1_weights = nn.Parameter(torch.randn(k * d, out) / math.sqrt(d))
        self.bn1 = nn.BatchNorm1d(k)
        self.bn2 = nn.BatchNorm1d(out)
        self.context_gating = PortGating(out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x [B, D, N, 1]
        b, d, n = x.shape[0], self.d, x.shape[2]
        x = x.transpose(1, 3).contiguous().view(b, n, d)
        act = torch.matmul(x, self.cluster_weights)
        act = self.bn1(act.view(-1, self.k)).view(b, n, self.k)
        act = F.softmax(act, dim=-1)
        a = act.sum(-2, keepdim=True) * self.cluster_weights2  # [B, D, K]
        vlad = torch.matmul(act.transpose(2, 1), x).transpose(2, 1)  # [B, D, K]
        vlad = F.normalize(vlad - a, dim=1)
        vlad = F.normalize(vlad.reshape(b, -1), dim=1)
        vlad = self.bn2(torch.matmul(vlad, self.hidden1_weights))
        return self.context_gating(vlad)


class PortPNVLAD(nn.Module):
    """``forward(points float32 [B, N, 3]) -> float32 [B, 256]`` (not L2-normalised, as the
    port returns it)."""

    def __init__(self, num_points: int = 4096, output_dim: int = 256) -> None:
        super().__init__()
        self.point_net = PortPointNet(num_points)
        self.net_vlad = PortNetVLAD(1024, 64, output_dim)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.net_vlad(self.point_net(points.unsqueeze(1)))
