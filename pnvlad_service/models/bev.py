"""bev-netvlad: a bird's-eye-view image of the points, a small 2-D CNN and PointNetVLAD's head.

Not the paper's network. PointNet sees each point alone until the pooling; on the benchmark it
levels off at recall@1% 87-88 % whatever its size, loss, mining or augmentation (docs/TRAINING.md,
runs 1-27). Here the points are first counted into an image of ``bev_grid`` x ``bev_grid`` cells
over x, y in [-1, 1] with ``bev_height_bins`` channels (one height slice of ``bev_z_range`` each,
log(1 + count) per cell), so neighbouring structure is next to each other before any layer runs;
3x3 convolutions (batch norm, ReLU) turn it into a ``bev_cells`` x ``bev_cells`` map of
``bev_feature_dim`` features, and PN_VLAD's NetVLAD head (:mod:`.netvlad`: soft assignment to K
clusters, residual sums, normalisations, fully connected layer, context gating) pools its cells
as PN_VLAD pools points. The submaps keep the world's axes (x east, y north), so no rotation
invariance is needed; a translation moves the image and NetVLAD's sums do not see where a
feature is.

The image does not depend on the points' order (counts are integers, exact in float32) nor,
apart from density, on how many there are: the network's cost is that of the image (about
0.3 GFLOP a cloud for :meth:`ModelConfig.bev`), the same for 1,024 or 4,096 points.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.heading import canonical_heading
from pnvlad_service.models.netvlad import NetVLAD


def bev_image(points: torch.Tensor, cfg: ModelConfig) -> torch.Tensor:
    """float32 [B, Z, G, G]: log(1 + points counted) in each cell of x, y in [-1, 1] (G =
    ``bev_grid``; row = y, column = x, from -1) and height slice of ``bev_z_range`` (Z =
    ``bev_height_bins``; z below or above the range counts in the first or last slice).

    ``points``: float [B, N, 3]; points with x or y outside [-1, 1] are not counted (a cell on
    the border would otherwise collect everything beyond it)."""
    b = points.shape[0]
    g, z = cfg.bev_grid, cfg.bev_height_bins
    lo, hi = cfg.bev_z_range
    p = points.float()
    x, y = p[..., 0], p[..., 1]
    inside = (x >= -1) & (x <= 1) & (y >= -1) & (y <= 1)
    ix = ((x + 1) * (g / 2)).floor().clamp_(0, g - 1).long()  # x = 1 belongs to the last cell
    iy = ((y + 1) * (g / 2)).floor().clamp_(0, g - 1).long()
    iz = ((p[..., 2] - lo) * (z / (hi - lo))).floor().clamp_(0, z - 1).long()
    batch = torch.arange(b, device=p.device).unsqueeze(1)
    flat = ((batch * z + iz) * g + iy) * g + ix
    counts = torch.zeros(b * z * g * g, device=p.device)
    counts.index_add_(0, flat.reshape(-1), inside.reshape(-1).float())
    return torch.log1p(counts).reshape(b, z, g, g)


class BEVNetVLAD(nn.Module):
    """``forward(points float32 [B, N, 3]) -> float32 [B, output_dim]``, rows of unit L2 norm.

    The same interface as :class:`.pointnetvlad.PointNetVLAD` (``cfg``, ``forward``), so
    training, the store and the encoder take either."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        if cfg.arch != "bev-netvlad":
            raise ValueError(f"BEVNetVLAD needs arch 'bev-netvlad', got {cfg.arch!r}")
        self.cfg = cfg
        layers: list[nn.Module] = []
        c = cfg.bev_height_bins
        for w, s in zip(cfg.bev_widths, cfg.bev_strides, strict=True):
            layers += [nn.Conv2d(c, w, 3, s, 1, bias=False), nn.BatchNorm2d(w), nn.ReLU(True)]
            c = w
        layers.append(nn.Conv2d(c, cfg.bev_feature_dim, 1))
        self.cnn = nn.Sequential(*layers)
        self.pool = NetVLAD(
            cfg.bev_feature_dim, cfg.cluster_size, cfg.output_dim, cfg.vlad_batch_norm, cfg.gating
        )

    def cell_features(self, points: torch.Tensor) -> torch.Tensor:
        """The feature map's cells as NetVLAD's points: [B, M, D] (M = ``bev_cells`` squared),
        each L2-normalised when ``cfg.point_l2_norm`` (as the paper normalises point features)."""
        if points.ndim != 3 or points.shape[-1] != 3:
            raise ValueError(f"expected points [B, N, 3], got {list(points.shape)}")
        if self.cfg.canonical_heading:
            points = canonical_heading(points)
        f = self.cnn(bev_image(points, self.cfg)).float().flatten(2).transpose(1, 2)
        return F.normalize(f, dim=2) if self.cfg.point_l2_norm else f

    def head(self, cells: torch.Tensor) -> torch.Tensor:
        """Descriptors [B, output_dim] (unit rows) of :meth:`cell_features` [B, M, D]: NetVLAD,
        the fully connected layer, gating, L2."""
        return F.normalize(self.pool(cells), dim=1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.head(self.cell_features(points))
