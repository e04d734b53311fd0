"""training.augment: each perturbation checked against what it must preserve or bound,
computed here from the input (norms, heights, which points exist, the drawn ranges)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pnvlad_service.errors import InputError  # noqa: E402
from pnvlad_service.training.augment import AugmentSection, augment  # noqa: E402
from pnvlad_service.training.config import TrainConfig  # noqa: E402


def _clouds(b: int = 6, p: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand((b, p, 3), generator=g) * 2 - 1


def test_off_returns_the_input_itself() -> None:
    x = _clouds()
    assert augment(x, AugmentSection(), 1) is x
    assert not AugmentSection().active and AugmentSection(jitter=0.1).active


def test_yaw_turns_each_cloud_rigidly_about_z_within_the_bound() -> None:
    x = _clouds()
    y = augment(x, AugmentSection(yaw_deg=30.0), 7)
    assert torch.equal(y[..., 2], x[..., 2])
    assert torch.allclose(y[..., :2].norm(dim=-1), x[..., :2].norm(dim=-1), atol=1e-5)
    for b in range(x.shape[0]):  # one angle a cloud, found by least squares
        a, *_ = np.linalg.lstsq(x[b, :, :2].numpy(), y[b, :, :2].numpy(), rcond=None)
        angle = math.degrees(math.atan2(a[0, 1], a[0, 0]))
        assert abs(angle) <= 30.0 + 1e-3
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        rot = np.array([[c, s], [-s, c]])  # row vectors: y = x @ rot
        np.testing.assert_allclose(a, rot, atol=1e-4)


def test_quarter_turns_turn_each_cloud_by_a_multiple_of_90_degrees() -> None:
    x = _clouds(b=32)
    cfg = AugmentSection(quarter_turns=True)
    assert cfg.active
    y = augment(x, cfg, 3)
    turns = set()
    for b in range(x.shape[0]):
        a, *_ = np.linalg.lstsq(x[b, :, :2].numpy(), y[b, :, :2].numpy(), rcond=None)
        angle = math.degrees(math.atan2(a[0, 1], a[0, 0])) % 360.0
        k = round(angle / 90.0) % 4
        assert abs(angle - 90.0 * round(angle / 90.0)) < 1e-3  # a whole quarter, nothing between
        turns.add(k)
    assert turns == {0, 1, 2, 3}  # all four drawn in 32 clouds
    # With yaw_deg the quarter turn comes on top of the small turn: within 5 degrees of one.
    y = augment(x, AugmentSection(quarter_turns=True, yaw_deg=5.0), 4)
    for b in range(x.shape[0]):
        a, *_ = np.linalg.lstsq(x[b, :, :2].numpy(), y[b, :, :2].numpy(), rcond=None)
        angle = math.degrees(math.atan2(a[0, 1], a[0, 0]))
        assert abs(angle - 90.0 * round(angle / 90.0)) <= 5.0 + 1e-3


def test_dropout_and_erasing_keep_p_points_all_taken_from_the_cloud() -> None:
    x = _clouds(p=500)
    y = augment(x, AugmentSection(dropout=0.5, erase_p=1.0, erase_size=0.3), 3)
    assert y.shape == x.shape
    for b in range(x.shape[0]):
        rows = {tuple(r) for r in x[b].tolist()}
        out = [tuple(r) for r in y[b].tolist()]
        assert all(r in rows for r in out)
        # at most half dropped, plus the block: never all, and copies refill the rest
        assert 0.2 * len(rows) < len(set(out)) < len(rows)


def test_erasing_empties_a_block() -> None:
    x = _clouds(b=8, p=2000, seed=4)
    y = augment(x, AugmentSection(erase_p=1.0, erase_size=0.4), 5)
    for b in range(x.shape[0]):
        kept = {tuple(r) for r in y[b].tolist()}
        gone = np.array([r for r in x[b].tolist() if tuple(r) not in kept])
        assert len(gone) > 0
        # the removed points fit in a square of 0.4 of the extent (2) in x and y
        assert (gone[:, :2].max(0) - gone[:, :2].min(0) <= 0.8 + 1e-6).all()


def test_shift_scale_and_jitter_stay_within_their_bounds() -> None:
    x = _clouds()
    shifted = augment(x, AugmentSection(shift=0.1), 2)
    d = shifted - x
    assert torch.allclose(d, d[:, :1].expand_as(d), atol=1e-6)  # one shift a cloud
    assert (d[..., :2].abs() <= 0.1 + 1e-6).all() and (d[..., 2] == 0).all()
    scaled = augment(x, AugmentSection(scale=0.05), 2)
    ratio = scaled / x
    assert ((ratio - 1).abs() <= 0.05 + 1e-5).all()
    jit = augment(x, AugmentSection(jitter=0.01), 2) - x
    assert (jit.abs() <= 0.03 + 1e-6).all() and 0.005 < float(jit.std()) < 0.015


def test_the_same_seed_repeats_and_another_differs() -> None:
    cfg = AugmentSection(yaw_deg=5, shift=0.02, scale=0.03, jitter=0.002, dropout=0.2, erase_p=0.3)
    x = _clouds()
    assert torch.equal(augment(x, cfg, 9), augment(x, cfg, 9))
    assert not torch.equal(augment(x, cfg, 9), augment(x, cfg, 10))


def test_extra_channels_travel_with_their_point_and_are_not_moved() -> None:
    x = _clouds(p=300)
    tag = torch.rand((x.shape[0], x.shape[1], 7), generator=torch.Generator().manual_seed(2))
    xt = torch.cat([x, tag], dim=2)
    cfg = AugmentSection(dropout=0.4, erase_p=1.0, yaw_deg=20, scale=0.1, shift=0.1, jitter=0.01)
    y = augment(xt, cfg, 11)
    assert y.shape == xt.shape
    # the same seed moves x, y and z as it moves a cloud without the extra channels
    torch.testing.assert_close(y[..., :3], augment(x, cfg, 11))
    for b in range(x.shape[0]):  # every output point carries the channels of one input point
        rows = {tuple(r) for r in tag[b].tolist()}
        assert all(tuple(r) in rows for r in y[b, :, 3:].tolist())


def test_the_config_names_a_bad_augment_field() -> None:
    cfg = TrainConfig.from_mapping({"train": {"augment": {"yaw_deg": 5}}})
    assert cfg.train.augment.yaw_deg == 5 and cfg.train.augment.active
    with pytest.raises(InputError, match="dropout"):
        TrainConfig.from_mapping({"train": {"augment": {"dropout": 1.5}}})
    with pytest.raises(InputError, match="spin"):
        TrainConfig.from_mapping({"train": {"augment": {"spin": 1}}})
