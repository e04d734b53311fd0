"""models.heading: a cloud's dominant direction (modulo a quarter turn) and the cloud turned to
it, on a synthetic street whose direction is known by construction.

The street (normalised units): a row of box-like buildings along x on each side, facades at
y = +-0.4, and some clutter between them. Turned by theta, its dominant direction is theta
modulo 90 degrees; the expected angle is wrapped to [-45, 45) degrees here, by hand.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.models.config import ModelConfig, config_sha256
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.heading import canonical_heading, dominant_angle

#: How close the angle comes on the street. The estimator reads gradients of a 64 x 64 image
#: (bilinear counts, two blurs) and leans a little towards the image's axes: measured worst
#: about 1.1 degrees (2.5 with nearest-cell counts and one blur).
TOL_DEG = 1.5

REPO = Path(__file__).resolve().parents[2]


def street(seed: int, n: int = 4096) -> np.ndarray:
    """float64 [n, 3]: 85 % of the points on the outlines of boxes along x (|y| from 0.4 to
    0.5, 0.2 to 0.4 long, gaps of 0.04 to 0.1), 15 % clutter on the street; all within a
    radius of 0.95 so that no turn pushes a point out of [-1, 1]."""
    rng = np.random.default_rng(seed)
    edges = []
    for side in (-1.0, 1.0):
        x0 = -0.78
        while x0 < 0.68:
            x1 = min(x0 + rng.uniform(0.2, 0.4), 0.78)
            y0, y1 = 0.4 * side, 0.5 * side
            edges += [
                ((x0, y0), (x1, y0)),
                ((x0, y1), (x1, y1)),
                ((x0, y0), (x0, y1)),
                ((x1, y0), (x1, y1)),
            ]
            x0 = x1 + rng.uniform(0.04, 0.1)
    a = np.array([e[0] for e in edges])
    b = np.array([e[1] for e in edges])
    lengths = np.linalg.norm(b - a, axis=1)
    m = int(0.85 * n)
    k = rng.choice(len(edges), m, p=lengths / lengths.sum())
    xy = a[k] + (b[k] - a[k]) * rng.uniform(0, 1, (m, 1)) + rng.normal(0, 0.003, (m, 2))
    walls = np.column_stack([xy, rng.uniform(-0.05, 0.1, m)])
    clutter = np.column_stack([rng.uniform(-0.6, 0.6, (n - m, 2)), rng.uniform(-0.05, 0.05, n - m)])
    out = np.vstack([walls, clutter])
    assert np.hypot(out[:, 0], out[:, 1]).max() < 0.95
    return out


def turned(points: np.ndarray, deg: float) -> np.ndarray:
    """``points`` turned about z by ``deg`` degrees (counter-clockwise), float64."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def wrapped(deg: float) -> float:
    """``deg`` modulo 90, in [-45, 45)."""
    return (deg + 45.0) % 90.0 - 45.0


def angle_deg(points: np.ndarray) -> float:
    return math.degrees(float(dominant_angle(torch.tensor(points[None], dtype=torch.float32))[0]))


def quarter_gap(a: float, b: float) -> float:
    """|a - b| modulo 90 degrees (0 to 45)."""
    return abs(wrapped(a - b))


@pytest.mark.parametrize("theta", [0.0, 7.0, 22.5, 31.0, 44.0, 45.0, 60.0, 90.0, 137.0, -100.0])
def test_dominant_angle_is_the_turn_modulo_a_quarter(theta: float) -> None:
    a = angle_deg(turned(street(0), theta))
    assert -45.0 <= a < 45.0
    assert quarter_gap(a, wrapped(theta)) <= TOL_DEG, (a, wrapped(theta))


@settings(max_examples=25, deadline=None)
@given(theta=st.floats(-180.0, 180.0), seed=st.integers(0, 5))
def test_dominant_angle_at_any_turn(theta: float, seed: int) -> None:
    a = angle_deg(turned(street(seed), theta))
    assert -45.0 <= a < 45.0
    assert quarter_gap(a, wrapped(theta)) <= TOL_DEG


@pytest.mark.parametrize("theta", [0.0, 13.0, 38.0, 71.0, 180.0, -123.0])
def test_canonical_heading_turns_by_minus_the_angle(theta: float) -> None:
    base = street(1)
    pts = turned(base, theta)
    x = torch.tensor(pts[None], dtype=torch.float32)
    out = canonical_heading(x)[0].double().numpy()
    a = angle_deg(pts)
    # The cloud is turned by -angle, point by point (checked on every point).
    np.testing.assert_allclose(out, turned(pts, -a), rtol=0, atol=1e-5)
    # Turned to its dominant direction, it has none left to turn by.
    assert quarter_gap(angle_deg(out), 0.0) <= TOL_DEG
    # The same place at any heading comes out at one of four headings: the turn taking the
    # unturned street's canonical cloud onto this one (least squares over the points, which
    # correspond row by row) is a multiple of 90 degrees.
    ref = canonical_heading(torch.tensor(base[None], dtype=torch.float32))[0].double().numpy()
    cross = (ref[:, 0] * out[:, 1] - ref[:, 1] * out[:, 0]).sum()
    dot = (ref[:, 0] * out[:, 0] + ref[:, 1] * out[:, 1]).sum()
    between = math.degrees(math.atan2(cross, dot))
    assert quarter_gap(between, 0.0) <= TOL_DEG, between
    # A plain check of that turn on one point.
    c, s = math.cos(math.radians(between)), math.sin(math.radians(between))
    np.testing.assert_allclose(
        out[0, :2], [c * ref[0, 0] - s * ref[0, 1], s * ref[0, 0] + c * ref[0, 1]], atol=1e-3
    )


def test_channels_after_xy_are_unchanged() -> None:
    pts = turned(street(2, n=1024), 33.0)
    extra = np.random.default_rng(2).normal(size=(1024, 7))
    x = torch.tensor(np.column_stack([pts, extra])[None], dtype=torch.float32)  # [1, N, 10]
    out = canonical_heading(x)
    assert out.shape == x.shape
    assert torch.equal(out[..., 2:], x[..., 2:])  # z and the seven features
    # x and y did turn.
    assert (out[..., :2] - x[..., :2]).abs().max() > 0.1
    # The features do not change the angle: it is read from x, y alone.
    assert dominant_angle(x)[0] == dominant_angle(x[..., :3])[0]


def test_a_batch_gives_each_clouds_own_angle() -> None:
    thetas = [0.0, 17.0, -29.0, 100.0, 41.0]
    batch = np.stack([turned(street(k), t) for k, t in enumerate(thetas)])
    x = torch.tensor(batch, dtype=torch.float32)
    together = dominant_angle(x)
    alone = torch.cat([dominant_angle(x[k : k + 1]) for k in range(len(thetas))])
    assert together.shape == (len(thetas),)
    assert together.dtype == torch.float32
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)
    torch.testing.assert_close(
        canonical_heading(x),
        torch.cat([canonical_heading(x[k : k + 1]) for k in range(len(thetas))]),
        rtol=0,
        atol=1e-5,
    )


@pytest.mark.parametrize(
    "cloud",
    [
        torch.rand(3, 2048, 3) * 2 - 1,  # uniform noise
        torch.rand(1, 512, 3) * 6 - 3,  # most points outside [-1, 1]
        torch.zeros(1, 100, 3),  # every point in one cell
        torch.full((1, 10, 3), 5.0),  # nothing inside the image at all
    ],
    ids=["noise", "outside", "one-cell", "empty-image"],
)
def test_formless_clouds_give_finite_output(cloud: torch.Tensor) -> None:
    a = dominant_angle(cloud)
    assert torch.isfinite(a).all()
    assert ((a >= -math.pi / 4) & (a < math.pi / 4)).all()
    out = canonical_heading(cloud)
    assert torch.isfinite(out).all()
    # A turn about z keeps each point's distance from the z axis.
    torch.testing.assert_close(out[..., :2].norm(dim=-1), cloud[..., :2].norm(dim=-1))


# --------------------------------------------------------------------------------------------
# ModelConfig.canonical_heading

#: A small bev-netvlad (as tests/models/test_bev.py's): fast on a CPU.
BEV = dict(
    bev_grid=16,
    bev_height_bins=3,
    bev_z_range=(-0.5, 0.5),
    bev_widths=(8, 16),
    bev_strides=(1, 2),
    bev_feature_dim=16,
    cluster_size=4,
    output_dim=32,
)


def test_config_hash_leaves_canonical_heading_out_when_false() -> None:
    # A bundle written before the field existed records its model's hash: it must not change.
    manifest = json.loads((REPO / "tests/index/bundle_v1/manifest.json").read_text())
    old = manifest["model"]
    assert "canonical_heading" not in old["config"]
    cfg = ModelConfig.model_validate(old["config"])
    assert config_sha256(cfg) == old["config_sha256"]
    assert config_sha256(cfg.model_copy(update={"canonical_heading": True})) != old["config_sha256"]
    # bev-netvlad: the hash of the canonical JSON without the field (nor local_k at 0, nor
    # embed_scales empty).
    for overrides in (BEV, {}):
        cfg = ModelConfig.bev(**overrides)
        doc = {
            k: v
            for k, v in cfg.model_dump(mode="json").items()
            if k not in ("canonical_heading", "local_k", "embed_scales")
        }
        text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
        assert config_sha256(cfg) == hashlib.sha256(text.encode()).hexdigest()
        on = ModelConfig.bev(**overrides, canonical_heading=True)
        assert config_sha256(on) != config_sha256(cfg)
        assert ModelConfig.model_validate(on.model_dump(mode="json")) == on


@pytest.mark.parametrize(
    "cfg",
    [
        ModelConfig.bev(**BEV),
        ModelConfig.compact(
            num_points=256,
            stem_widths=(8,),
            trunk_widths=(16, 32),
            tnet_point_widths=(8, 16),
            tnet_fc_widths=(16, 8),
            cluster_size=4,
            output_dim=16,
        ),
    ],
    ids=["bev-netvlad", "pointnetvlad"],
)
def test_a_model_with_canonical_heading_sees_the_canonical_cloud(cfg: ModelConfig) -> None:
    torch.manual_seed(0)
    plain = build_model(cfg).eval()
    turning = build_model(cfg.model_copy(update={"canonical_heading": True})).eval()
    turning.load_state_dict(plain.state_dict())
    n = cfg.num_points if cfg.arch != "bev-netvlad" else 1024
    x = torch.tensor(
        np.stack([turned(street(k, n=n), t) for k, t in enumerate([20.0, -35.0])]),
        dtype=torch.float32,
    )
    with torch.no_grad():
        got = turning(x)
        torch.testing.assert_close(got, plain(canonical_heading(x)), rtol=0, atol=1e-5)
        assert (got - plain(x)).abs().max() > 1e-3  # the switch does something
