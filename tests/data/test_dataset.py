"""data.dataset: submaps of any point count read for training, fitted to the model's count."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.dataset import fit_points, load_clouds, read_submap
from pnvlad_service.errors import InputError


def test_read_submap_bin_of_any_count_and_npy(tmp_path: Path) -> None:
    rows = [(0.5, -0.25, 0.125), (-1.0, 0.75, 0.0), (0.0, 0.5, -0.5)]
    (tmp_path / "a.bin").write_bytes(b"".join(struct.pack("<3d", *r) for r in rows))
    np.save(tmp_path / "b.npy", np.array(rows))
    for name in ("a.bin", "b.npy"):
        pts = read_submap(tmp_path / name)
        assert pts.dtype == np.float32 and pts.tolist() == [list(r) for r in rows]


def test_read_submap_refuses_a_partial_triple_and_a_missing_file(tmp_path: Path) -> None:
    (tmp_path / "odd.bin").write_bytes(struct.pack("<4d", 0, 0, 0, 0))
    with pytest.raises(InputError, match="4 float64 values, not a multiple of 3"):
        read_submap(tmp_path / "odd.bin")
    with pytest.raises(InputError, match="submap file not found") as exc:
        read_submap(tmp_path / "none.bin")
    assert exc.value.source == str(tmp_path / "none.bin")


def test_load_clouds_fits_every_submap_to_the_point_count(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    sizes = [10, 16, 40]
    paths = []
    for k, n in enumerate(sizes):
        paths.append(tmp_path / f"{k}.bin")
        paths[-1].write_bytes(rng.uniform(-1, 1, (n, 3)).astype("<f8").tobytes())
    clouds = load_clouds(paths, 16, workers=2)
    assert clouds.shape == (3, 16, 3) and clouds.dtype == np.float32
    for k, path in enumerate(paths):
        expected = fit_points(read_submap(path), 16)
        assert np.array_equal(clouds[k], expected)
        # every fitted row is a row of the file
        rows = {tuple(r) for r in read_submap(path).tolist()}
        assert all(tuple(r) in rows for r in clouds[k].tolist())


def test_load_clouds_takes_shape_features_on_the_whole_submap(tmp_path: Path) -> None:
    from pnvlad_service.models.local_shape import shape_feature_fn, shape_features

    pts = np.random.default_rng(1).normal(size=(300, 3))
    path = tmp_path / "a.bin"
    path.write_bytes(pts.astype("<f8").tobytes())
    assert shape_feature_fn(0) is None  # a plain model: coordinates only
    out = load_clouds([path], 64, point_features=shape_feature_fn(12))
    assert out.shape == (1, 64, 10)
    whole = read_submap(path)
    rows = [int(np.flatnonzero((whole == r).all(axis=1))[0]) for r in out[0, :, :3]]
    np.testing.assert_array_equal(out[0, :, :3], fit_points(whole, 64))
    # the features of each kept point are those it has in the whole submap, not in the subset
    np.testing.assert_allclose(out[0, :, 3:], shape_features(whole, 12)[rows], atol=1e-6)
    subset_only = shape_features(out[0, :, :3], 12)
    assert np.abs(subset_only - out[0, :, 3:]).max() > 0.1


def test_training_sets_of_two_datasets_pool_with_offsets(tmp_path) -> None:
    from pnvlad_service.data.dataset import training_set_from_tuples
    from pnvlad_service.data.splits import TrainingTuples

    def tt(name: str, n: int) -> TrainingTuples:
        north = np.arange(n) * 6.0
        pos = [
            np.array([j for j in range(n) if j != i and abs(north[j] - north[i]) <= 10])
            for i in range(n)
        ]
        near = [np.array([j for j in range(n) if abs(north[j] - north[i]) <= 50]) for i in range(n)]
        return TrainingTuples(
            name, [f"{name}/r/p/{i}.bin" for i in range(n)], pos, near, north, np.zeros(n)
        )

    ts = training_set_from_tuples([tt("a", 20), tt("b", 30)], tmp_path)
    assert len(ts) == 50
    assert ts.paths[25] == tmp_path / "b" / "r" / "p" / "5.bin"
    assert ts.positives[25].tolist() == [24, 26]  # b's 4 and 6, offset by 20
    assert ts.datasets == [("a", 0, 20), ("b", 20, 50)]  # what data.dataset_weights names
    # a negative of a b-submap is any a-submap (never near) or a b-submap beyond 50 m
    mask = ts.negative_mask(25, np.arange(50))
    assert mask[:20].all()
    assert mask[20:].tolist() == [abs(k - 5) * 6.0 > 50 for k in range(30)]
