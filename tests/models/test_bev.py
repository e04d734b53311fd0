"""models.bev: the bird's-eye image against a plain loop, the network's invariants, and the
encoder, store and FLOP count on bev-netvlad."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.models.bev import BEVNetVLAD, bev_image
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import Encoder, bf16_supported
from pnvlad_service.models.store import config_sha256, load_model, save_model
from tests.models.helpers import clouds

#: A small bev-netvlad: 16 x 16 x 3 image, two convolutions, K = 4, 32-d.
SMALL = ModelConfig.bev(
    bev_grid=16,
    bev_height_bins=3,
    bev_z_range=(-0.5, 0.5),
    bev_widths=(8, 16),
    bev_strides=(1, 2),
    bev_feature_dim=16,
    cluster_size=4,
    output_dim=32,
)


def loop_image(points: np.ndarray, g: int, z: int, lo: float, hi: float) -> np.ndarray:
    """The image by a plain loop over points: cell = floor((v + 1) g / 2), the top edge in the
    last cell; x or y outside [-1, 1] dropped; z clamped into the slices (float32 arithmetic,
    as the model's, so a point on a cell's edge falls on the same side)."""
    f = np.float32
    counts = np.zeros((len(points), z, g, g))
    for b, cloud in enumerate(points):
        for x, y, h in cloud.astype(f):
            if not (-1 <= x <= 1 and -1 <= y <= 1):
                continue
            col = min(math.floor((x + f(1)) * f(g / 2)), g - 1)
            row = min(math.floor((y + f(1)) * f(g / 2)), g - 1)
            sl = min(max(math.floor((h - f(lo)) * f(z / (hi - lo))), 0), z - 1)
            counts[b, sl, row, col] += 1
    return np.log1p(counts)


def test_image_hand_worked() -> None:
    """4 x 4 cells of 0.5, 2 slices over z in [0, 1]: (-0.9, -0.9) is row 0, column 0; x = 1
    is the last column; z below the range is slice 0, above it slice 1; y = 1.5 is dropped."""
    cfg = ModelConfig.bev(bev_grid=4, bev_height_bins=2, bev_z_range=(0.0, 1.0))
    pts = torch.tensor(
        [
            [
                [-0.9, -0.9, 0.2],
                [-0.8, -0.6, 0.4],  # same cell and slice: a count of 2
                [1.0, 0.1, 0.7],  # row 2, column 3, slice 1
                [0.2, -0.3, -5.0],  # row 1, column 2, slice 0 (clamped)
                [0.2, -0.3, 9.0],  # the same cell, slice 1 (clamped)
                [0.0, 1.5, 0.5],  # outside in y: not counted
            ]
        ]
    )
    img = bev_image(pts, cfg)
    want = torch.zeros(1, 2, 4, 4)
    want[0, 0, 0, 0] = math.log(3)
    want[0, 1, 2, 3] = math.log(2)
    want[0, 0, 1, 2] = math.log(2)
    want[0, 1, 1, 2] = math.log(2)
    assert torch.equal(img, want)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(
            *(st.floats(-1.25, 1.25, width=32) | st.sampled_from([-1.0, -0.875, 0.5, 1.0]),) * 3
        ),
        min_size=1,
        max_size=40,
    )
)
def test_image_matches_a_plain_loop(pts: list[tuple[float, float, float]]) -> None:
    arr = np.array([pts], dtype=np.float32)
    got = bev_image(torch.from_numpy(arr), SMALL).numpy()
    want = loop_image(arr, 16, 3, -0.5, 0.5)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


def _trained_like(cfg: ModelConfig = SMALL) -> torch.nn.Module:
    """Batch norms with non-trivial running statistics, in eval mode."""
    torch.manual_seed(0)
    model = build_model(cfg).train()
    with torch.no_grad():
        for i in range(3):
            model(clouds(4, seed=10 + i))
    return model.eval()


def test_descriptor_ignores_point_order_and_batch_company() -> None:
    model = _trained_like()
    x = clouds(3, seed=1)
    with torch.no_grad():
        ref = model(x)
        shuffled = model(x[:, torch.randperm(x.shape[1])])
        alone = model(x[1:2])
    assert ref.shape == (3, 32)
    torch.testing.assert_close(ref.norm(dim=1), torch.ones(3))
    assert torch.equal(shuffled, ref)  # integer counts: exactly the same image
    torch.testing.assert_close(alone[0], ref[1], rtol=0, atol=1e-6)
    assert (ref[0] - ref[1]).abs().max() > 1e-3  # different clouds, different descriptors


def test_a_shift_by_whole_cells_moves_the_image() -> None:
    """Points shifted by 3 cells in x and -2 in y (none crossing the border) give the image
    rolled by 3 columns and -2 rows: where a structure is does not change what it looks like."""
    g = torch.Generator().manual_seed(5)
    cells = torch.randint(2, 12, (1, 300, 2), generator=g).float()  # columns, rows 2..11
    xy = (cells + torch.rand(1, 300, 2, generator=g) * 0.8 + 0.1) * (2 / 16) - 1
    z = torch.rand(1, 300, 1, generator=g) - 0.5
    pts = torch.cat([xy, z], dim=2)
    moved = pts.clone()
    moved[..., 0] += 3 * 2 / 16
    moved[..., 1] -= 2 * 2 / 16
    img = bev_image(pts, SMALL)
    assert torch.equal(bev_image(moved, SMALL), img.roll((-2, 3), dims=(2, 3)))


def test_encoder_store_and_bfloat16(tmp_path: Path) -> None:
    model = _trained_like()
    x = clouds(5, seed=2)
    with torch.no_grad():
        ref = model(x).numpy()
    enc = Encoder(model, SMALL)
    np.testing.assert_allclose(enc.embed(x.numpy()), ref, rtol=0, atol=1e-6)
    assert model.training is False  # the encoder keeps a copy and leaves the caller's module
    np.testing.assert_allclose(enc.embed(x[0].double().numpy()), ref[:1], rtol=0, atol=1e-6)
    save_model(tmp_path / "m", model, SMALL)
    loaded, cfg = load_model(tmp_path / "m")
    assert cfg == SMALL and isinstance(loaded, BEVNetVLAD)
    again = Encoder.from_checkpoint(tmp_path / "m").embed(x.numpy())
    np.testing.assert_array_equal(again, enc.embed(x.numpy()))
    if bf16_supported():
        low = Encoder(model, SMALL, dtype="bfloat16").embed(x.numpy())
        cos = (low * ref).sum(1)
        assert cos.min() > 0.99 and np.abs(low - ref).max() > 0  # close, yet really bfloat16
        # The convolutions in bfloat16, the NetVLAD head in float32 (more top-1s kept).
        with torch.no_grad():
            with torch.autocast("cpu", dtype=torch.bfloat16):
                cells = model.cell_features(x)
            assert cells.dtype == torch.float32
            want = model.head(cells).numpy()
        np.testing.assert_allclose(low, want, rtol=0, atol=1e-6)


def test_config_validation_flops_and_hash() -> None:
    with pytest.raises(ValueError, match="one stride per"):
        ModelConfig.bev(bev_widths=(8, 8), bev_strides=(1,))
    with pytest.raises(ValueError, match="1 or 2"):
        ModelConfig.bev(bev_widths=(8,), bev_strides=(3,))
    with pytest.raises(ValueError, match="low < high"):
        ModelConfig.bev(bev_z_range=(0.1, 0.1))
    with pytest.raises(ValueError, match="local_k"):
        ModelConfig.bev(local_k=8)
    with pytest.raises(ValueError, match="bev-netvlad"):
        BEVNetVLAD(ModelConfig.compact())
    # FLOPs by hand for SMALL: 16x16 cells, 3 -> 8 (3x3), 8 -> 16 (3x3, stride 2: 8x8 cells),
    # 16 -> 16 (1x1), NetVLAD over 64 cells (K 4, D 16), fc 64 -> 32, gating 32 x 32.
    hand = (
        2 * 256 * 3 * 8 * 9
        + 2 * 64 * 8 * 16 * 9
        + 2 * 64 * 16 * 16
        + 2 * 2 * 64 * 16 * 4
        + 2 * 4 * 16 * 32
        + 2 * 32 * 32
    )
    assert SMALL.flops_per_cloud() == hand == SMALL.flops_per_cloud(num_points=10)
    assert SMALL.bev_cells == 8
    # The bev fields are hashed for bev-netvlad, and change its hash.
    assert config_sha256(SMALL) != config_sha256(SMALL.model_copy(update={"bev_grid": 32}))
    assert config_sha256(ModelConfig.compact()) == config_sha256(
        ModelConfig.compact(bev_grid=32)  # a PointNet model ignores them
    )


@pytest.mark.parametrize("workers", [2, 1])
def test_a_crowded_encoder_runs_the_module_on_a_cloud_worker(workers: int) -> None:
    """bev-netvlad runs as its module on the torch thread's team alone, and on a single-threaded
    cloud worker while ``crowded_by`` says other work holds the cores (beside a busy core the
    team waits at every barrier); with one worker there is none, and it stays on the torch
    thread. The descriptors are the same."""
    import threading

    model = _trained_like()
    x = torch.rand(3, SMALL.num_points, 3) * 2 - 1
    enc = Encoder(model, SMALL, cloud_workers=workers)
    where: list[str] = []
    forward = enc._module_forward

    def recorded(*args):
        where.append(threading.current_thread().name.split("_")[0])
        return forward(*args)

    enc._module_forward = recorded
    try:
        alone = enc.embed(x.numpy())
        enc.crowded_by = lambda: True
        crowded = enc.embed(x.numpy())
    finally:
        enc.close()
    assert where == ["pnvlad-torch", "pnvlad-encoder" if workers > 1 else "pnvlad-torch"]
    assert np.abs(alone - crowded).max() < 1e-5
    with torch.no_grad():
        assert np.abs(crowded - model(x).numpy()).max() < 1e-5
