"""models.local_shape: the local shape features checked on hand-built neighbourhoods (a line,
a floor, a wall, a pole), against a plain per-point loop with brute-force neighbours, and for
the invariances the training augmentations rely on; then the encoders that take them (module
fast path, reference path and folded Encoder agree; given features equal computed ones)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.local_shape import (
    NUM_FEATURES,
    shape_features,
    split_inputs,
    with_shape_features,
)
from tests.models.helpers import clouds, trained_like

LIN, PLA, SCA, NZ, DZ, ENT, RK = range(NUM_FEATURES)


def _grid(a: np.ndarray, b: np.ndarray, n: int = 12) -> np.ndarray:
    """n x n points on the plane spanned by unit vectors a and b through the origin."""
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    return u.reshape(-1, 1) * a + v.reshape(-1, 1) * b


def test_a_line_is_linear_and_a_vertical_line_is_a_pole() -> None:
    t = np.linspace(-1, 1, 40)[:, None]
    flat = shape_features(t * np.array([[1.0, 0.0, 0.0]]), 8)
    np.testing.assert_allclose(flat[:, LIN], 1.0, atol=1e-6)
    np.testing.assert_allclose(flat[:, [PLA, SCA, DZ, ENT]], 0.0, atol=1e-6)
    pole = shape_features(t * np.array([[0.0, 0.0, 1.0]]), 8)
    np.testing.assert_allclose(pole[:, DZ], 1.0, atol=1e-6)


def test_a_floor_and_a_wall_are_planar_with_the_normal_up_and_level() -> None:
    ex, ey, ez = np.eye(3)
    floor = shape_features(_grid(ex, ey), 9)
    wall = shape_features(_grid(ex, ez), 9)
    inner = (np.abs(_grid(ex, ey)[:, :2]) < 0.8).all(axis=1)  # a full 3 x 3 neighbourhood
    for f in (floor, wall):
        np.testing.assert_allclose(f[inner][:, PLA], 1.0, atol=1e-6)  # l1 = l2, l3 = 0
        np.testing.assert_allclose(f[inner][:, [LIN, SCA]], 0.0, atol=1e-6)
        np.testing.assert_allclose(f[inner][:, ENT], math.log(2) / math.log(3), atol=1e-6)
    np.testing.assert_allclose(floor[:, NZ], 1.0, atol=1e-6)
    np.testing.assert_allclose(wall[:, NZ], 0.0, atol=1e-6)


def _by_loop(x: np.ndarray, k: int) -> np.ndarray:
    """The features computed point by point: brute-force neighbours, np.cov, np.linalg.eigh."""
    out = np.zeros((len(x), NUM_FEATURES))
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    rk = np.sqrt(np.sort(d2, axis=1)[:, k - 1])
    for i in range(len(x)):
        nb = x[np.argsort(d2[i], kind="stable")[:k]]
        lam, vec = np.linalg.eigh(np.cov(nb.T, bias=True))
        l3, l2, l1 = lam
        e = lam / lam.sum()
        out[i] = [
            (l1 - l2) / l1,
            (l2 - l3) / l1,
            l3 / l1,
            abs(vec[2, 0]),
            abs(vec[2, 2]),
            -(e * np.log(e)).sum() / math.log(3),
            np.clip(math.log(rk[i] / np.median(rk)), -3, 3),
        ]
    return out


def test_the_features_match_a_plain_per_point_loop() -> None:
    x = np.random.default_rng(3).normal(size=(150, 3)) * [1.0, 0.5, 0.2]
    np.testing.assert_allclose(shape_features(x, 10), _by_loop(x, 10), atol=2e-5)


def test_a_turn_about_z_a_shift_and_a_scaling_leave_the_features_unchanged() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(size=(300, 3)) * [1.0, 0.6, 0.3]
    c, s = math.cos(1.1), math.sin(1.1)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = 2.5 * (x @ rot.T) + [4.0, -2.0, 1.0]
    np.testing.assert_allclose(shape_features(moved, 12), shape_features(x, 12), atol=1e-4)


def test_degenerate_clouds_give_zeros_not_nans() -> None:
    same = np.ones((50, 3))
    assert not shape_features(same, 8).any()
    assert not shape_features(np.zeros((2, 3)), 8).any()  # fewer than 3 neighbours
    assert shape_features(np.zeros((0, 3)), 8).shape == (0, NUM_FEATURES)
    dup = np.concatenate([np.zeros((20, 3)), np.random.default_rng(0).normal(size=(30, 3))])
    assert np.isfinite(shape_features(dup, 8)).all()


def test_with_shape_features_appends_the_features_of_each_cloud() -> None:
    x = clouds(3, 200).numpy()
    out = with_shape_features(x, 10, workers=2)
    assert out.shape == (3, 200, 3 + NUM_FEATURES)
    np.testing.assert_array_equal(out[..., :3], x)
    for b in range(3):
        np.testing.assert_array_equal(out[b, :, 3:], shape_features(x[b], 10))


def test_split_inputs_takes_given_features_computes_missing_ones_and_names_bad_shapes() -> None:
    x = clouds(2, 100)
    xyz, f = split_inputs(x, 10)
    assert xyz is x and f.shape == (2, 100, NUM_FEATURES)
    np.testing.assert_allclose(f[1].numpy(), shape_features(x[1].numpy(), 10))
    given = torch.cat([x, f], dim=2)
    xyz2, f2 = split_inputs(given, 10)
    assert torch.equal(xyz2, x) and torch.equal(f2, f)
    assert split_inputs(x, 0)[1] is None
    with pytest.raises(InputError, match="points"):
        split_inputs(given, 0)  # a plain model takes x, y, z only
    with pytest.raises(InputError, match=r"3 \+ 7"):
        split_inputs(x[..., :2], 10)


def test_config_local_k_bounds_and_the_hash_of_plain_models_is_unchanged() -> None:
    from pnvlad_service.models.config import config_sha256

    with pytest.raises(ValueError, match="local_k"):
        ModelConfig.compact(local_k=2)
    assert ModelConfig.compact().input_dim == 3
    assert ModelConfig.compact(local_k=16).input_dim == 3 + NUM_FEATURES
    # The hashes of the previous release (before local_k existed), taken from its code.
    assert config_sha256(ModelConfig.compact()) == (
        "548485fa26f8de5a31547e91d497adbab18b36f53e884bca9aeb25f1422e91eb"
    )
    assert config_sha256(ModelConfig.paper()) == (
        "2db8ce785f1473c0483cfa9fac8c665adb3ad0f9662e04bbfe8420b4949fec0c"
    )
    assert config_sha256(ModelConfig.compact(local_k=16)) != config_sha256(ModelConfig.compact())


@pytest.mark.parametrize("input_transform", [True, False])
def test_the_encoders_agree_with_shape_features(input_transform: bool) -> None:
    cfg = ModelConfig.compact(num_points=200, local_k=10, input_transform=input_transform)
    model = trained_like(cfg)
    x = clouds(3, 200, seed=7)
    given = torch.from_numpy(with_shape_features(x.numpy(), 10))
    with torch.no_grad():
        fast = model(x)
        model.fast_path = False
        ref = model(x)
        model.fast_path = True
        fast_given = model(given)
    torch.testing.assert_close(fast, ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast_given, fast, atol=1e-6, rtol=0)
    enc = Encoder(model, cfg)
    np.testing.assert_allclose(enc.embed(x.numpy()), ref.numpy(), atol=1e-5)
    np.testing.assert_allclose(enc.embed(given.numpy()), ref.numpy(), atol=1e-5)
    # The features matter: without them (zeros) the descriptor changes.
    blank = given.clone()
    blank[..., 3:] = 0
    assert (enc.embed(blank.numpy()) - ref.numpy()).__abs__().max() > 1e-3
    with pytest.raises(InputError, match="shape features"):
        enc.embed(np.zeros((1, 200, 5), dtype=np.float32))


def test_training_gradients_of_the_fast_path_match_the_reference() -> None:
    cfg = ModelConfig.compact(num_points=200, local_k=10)
    model = trained_like(cfg).train()
    x = torch.from_numpy(with_shape_features(clouds(4, 200, seed=9).numpy(), 10))
    grads = []
    for fast in (True, False):
        model.zero_grad()
        model.fast_path = fast
        model(x).pow(3).sum().backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters()})
    for name, g in grads[0].items():
        torch.testing.assert_close(g, grads[1][name], atol=2e-4, rtol=1e-3, msg=name)
