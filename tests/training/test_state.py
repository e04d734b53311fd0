"""training.state: the data checked and fitted to the config before anything is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.dataset import EvalRun, TrainingSet
from pnvlad_service.training.config import TrainConfig
from pnvlad_service.training.runtime import Dist, Runtime
from pnvlad_service.training.state import prepare_data

torch = pytest.importorskip("torch")


def _line_set(tmp: Path, n: int, spacing: float) -> TrainingSet:
    """``n`` submaps of 16 points each ``spacing`` m along a line; positives within 10 m."""
    north = np.arange(n) * spacing
    paths = []
    for i in range(n):
        paths.append(tmp / f"{i}.npy")
        np.save(paths[-1], np.random.default_rng(i).uniform(-1, 1, (16, 3)))
    positives = [np.flatnonzero((np.abs(north - x) <= 10) & (north != x)) for x in north]
    return TrainingSet(paths, np.c_[north, np.zeros(n)], positives)


def test_prepare_data_fits_the_tuple_and_drops_a_one_run_validation(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ts = _line_set(tmp_path, 24, 5.0)  # 0..115 m: the middle anchors have 3 negatives
    cfg = TrainConfig().with_overrides({"model.num_points": 16, "train.workers": 1})
    one_run = EvalRun("r", [], np.zeros((0, 2)), [], np.zeros((0, 2)), [])
    rt = Runtime(Dist(), torch.device("cpu"))
    with caplog.at_level("WARNING"):
        data = prepare_data(cfg, rt, ts, [one_run], progress=False)
    assert (data.negatives, data.hard_negatives) == (2, 2)  # 3 negatives, one left for "other"
    assert data.val_runs == [] and "single run" in caplog.text
    assert data.anchors.tolist() == ts.anchors().tolist()
    assert data.clouds.shape == (24, 16, 3) and data.clouds.dtype == torch.float32
    np.testing.assert_array_equal(data.clouds[3].numpy(), np.load(ts.paths[3]).astype(np.float32))
    # in-batch mining draws its negatives from the batch: nothing to fit
    data = prepare_data(cfg.with_overrides({"train.mining": "in_batch"}), rt, ts, progress=False)
    assert (data.negatives, data.hard_negatives) == (18, 10)


def test_prepare_data_weights_the_datasets(tmp_path: Path) -> None:
    ts = _line_set(tmp_path, 24, 5.0)
    ts.datasets = [("near", 0, 12), ("far", 12, 24)]
    cfg = TrainConfig().with_overrides(
        {"model.num_points": 16, "train.workers": 1, "data.dataset_weights": {"far": 2}}
    )
    data = prepare_data(cfg, Runtime(Dist(), torch.device("cpu")), ts, progress=False)
    plain = ts.anchors()
    assert sorted(data.anchors.tolist()) == sorted(
        plain[plain < 12].tolist() + 2 * plain[plain >= 12].tolist()
    )
    assert data.clouds.shape[0] == 24  # the clouds are held once
