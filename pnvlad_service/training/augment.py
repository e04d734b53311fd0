"""Training-time augmentation of normalised submaps.

The published PointNetVLAD code trains on the submaps as stored. MinkLoc3D (Komorowski,
WACV 2021) showed that perturbing them during training lifts recall on unseen areas: its
training transform removes random points and a random block, jitters and shifts the cloud,
and turns it about the vertical. This module does the same to a batch of clouds on the
training device, every number drawn from one seed so that a resumed run repeats the
uninterrupted one step for step.

Every operation keeps ``P`` points a cloud (a removed point is replaced by a copy of a kept
one: max pooling and NetVLAD's soft assignment see the same cloud, slightly re-weighted), and
works in the normalised units the clouds are stored in (``metres = centre + scale * value``;
the benchmark's 20 m submaps span about [-1, 1], so 0.05 is about half a metre).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    import torch


class AugmentSection(BaseModel):
    """What the training step does to each cloud before embedding it (all off by default: the
    paper trains on the stored submaps)."""

    model_config = ConfigDict(extra="forbid")

    yaw_deg: float = Field(
        0.0, ge=0, le=180, description="Largest turn about the vertical (uniform in +-yaw)."
    )
    quarter_turns: bool = Field(
        False,
        description="Also turn each cloud by a random multiple of 90 degrees: for clouds whose "
        "heading is known only up to a quarter turn (single scans canonicalised by their "
        "dominant direction, models/heading.py), so the model does not tell the four apart.",
    )
    shift: float = Field(0.0, ge=0, description="Largest shift in x and y (normalised units).")
    scale: float = Field(0.0, ge=0, lt=1, description="Largest relative scaling (1 +- scale).")
    jitter: float = Field(0.0, ge=0, description="Std of per-point noise, clipped at 3 std.")
    dropout: float = Field(
        0.0, ge=0, lt=1, description="Largest share of points removed (uniform in [0, dropout])."
    )
    erase_p: float = Field(0.0, ge=0, le=1, description="Chance a cloud loses a random block.")
    erase_size: float = Field(
        0.25, gt=0, le=1, description="Side of the erased block, as a share of the cloud's extent."
    )

    @property
    def active(self) -> bool:
        return (
            any(
                v > 0
                for v in (
                    self.yaw_deg,
                    self.shift,
                    self.scale,
                    self.jitter,
                    self.dropout,
                    self.erase_p,
                )
            )
            or self.quarter_turns
        )


def _refill(x: torch.Tensor, keep: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """``x`` [B, P, C] with each point where ``keep`` [B, P] is False replaced by a random
    kept point of its cloud (a cloud with nothing kept is left as it was)."""
    import torch

    b, p, _ = x.shape
    keep = keep | ~keep.any(dim=1, keepdim=True)
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)  # kept points first
    n_keep = keep.sum(dim=1, keepdim=True)
    u = torch.rand((b, p), generator=g, device=x.device)
    pick = order.gather(1, (u * n_keep).long().clamp_max(p - 1))
    src = torch.where(keep, torch.arange(p, device=x.device).expand(b, p), pick)
    return x.gather(1, src.unsqueeze(-1).expand(b, p, x.shape[2]))


def augment(x: torch.Tensor, cfg: AugmentSection, seed: int) -> torch.Tensor:
    """A perturbed copy of ``x`` float [B, P, 3] (normalised clouds), drawn from ``seed``.
    Channels after the third (a point's shape features, ``models/local_shape.py``) travel
    with their point: a refilled point brings its own, and the turn, scaling, shift and
    jitter, which leave them unchanged, touch x, y and z only.

    In order: point dropout, block erasing, turn about z, scaling, shift, jitter. ``x`` is
    returned itself when ``cfg`` does nothing."""
    import torch

    if not cfg.active:
        return x
    g = torch.Generator(device=x.device)
    g.manual_seed(int(seed))
    b, p, _ = x.shape
    dev, dt = x.device, x.dtype

    def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(shape, generator=g, device=dev, dtype=dt)

    if cfg.dropout > 0:
        share = uniform(0.0, cfg.dropout, b, 1)
        x = _refill(x, torch.rand((b, p), generator=g, device=dev, dtype=dt) >= share, g)
    if cfg.erase_p > 0:
        lo, hi = x.amin(dim=1), x.amax(dim=1)  # [B, 3]
        centre = x[torch.arange(b, device=dev), torch.randint(0, p, (b,), generator=g, device=dev)]
        half = (hi - lo)[:, :2] * (cfg.erase_size / 2)
        inside = ((x[:, :, :2] - centre[:, None, :2]).abs() <= half[:, None]).all(dim=2)
        erase = uniform(0.0, 1.0, b, 1) < cfg.erase_p
        x = _refill(x, ~(inside & erase), g)
    if cfg.yaw_deg > 0 or cfg.quarter_turns:
        yaw = uniform(-math.radians(cfg.yaw_deg), math.radians(cfg.yaw_deg), b)
        if cfg.quarter_turns:
            quarters = torch.randint(0, 4, (b,), generator=g, device=dev).to(dt)
            yaw = yaw + quarters * (math.pi / 2)
        c, s = torch.cos(yaw), torch.sin(yaw)
        xy = torch.stack([c * x[..., 0].T - s * x[..., 1].T, s * x[..., 0].T + c * x[..., 1].T])
        x = torch.cat([xy.permute(2, 1, 0), x[..., 2:]], dim=2)
    if cfg.scale > 0:
        xyz = x[..., :3] * uniform(1.0 - cfg.scale, 1.0 + cfg.scale, b, 1, 1)
        x = torch.cat([xyz, x[..., 3:]], dim=2)
    if cfg.shift > 0:
        d = uniform(-cfg.shift, cfg.shift, b, 1, 2)
        x = torch.cat([x[..., :2] + d, x[..., 2:]], dim=2)
    if cfg.jitter > 0:
        noise = torch.randn((b, p, 3), generator=g, device=dev, dtype=dt) * cfg.jitter
        x = torch.cat([x[..., :3] + noise.clamp(-3 * cfg.jitter, 3 * cfg.jitter), x[..., 3:]], 2)
    return x
