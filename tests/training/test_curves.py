"""training.curves: a hand-written log read back, the smoothing worked by hand, the figure
written whole."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.training.curves import read_curve, smoothed, write_learning_curves


def _log(path: Path, lines: list[dict | str]) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    text = "\n".join(x if isinstance(x, str) else json.dumps(x) for x in lines)
    (path / "metrics.jsonl").write_text(text + "\n")
    return path


def test_read_curve_by_hand(tmp_path: Path) -> None:
    run = _log(
        tmp_path / "a",
        [
            {"event": "start", "step": 0, "time": 1000.0},
            {"event": "step", "step": 10, "loss": 0.8, "time": 1060.0},
            {
                "event": "val",
                "step": 10,
                "recall_at_1": 50.0,
                "recall_at_1pct": 60.0,
                "time": 1090.0,
            },
            {"event": "step", "step": 20, "loss": 0.4, "time": 1180.0},
            {"event": "start", "step": 20, "resumed": True, "time": 2000.0},  # a resume
            {"event": "step", "step": 30, "loss": 0.2, "time": 2060.0},
            '{"event": "step", "step": 40, "lo',  # cut short by a kill
        ],
    )
    c = read_curve(run)
    assert c.name == "a"
    np.testing.assert_allclose(c.minutes, [1.0, 3.0, 1060 / 60])
    np.testing.assert_allclose(c.loss, [0.8, 0.4, 0.2])
    np.testing.assert_allclose(c.val_minutes, [1.5])
    assert c.recall_at_1.tolist() == [50.0] and c.recall_at_1pct.tolist() == [60.0]


def test_smoothed_is_a_trailing_mean() -> None:
    np.testing.assert_allclose(smoothed(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])


def test_a_log_without_steps_is_refused(tmp_path: Path) -> None:
    run = _log(tmp_path / "b", [{"event": "start", "step": 0, "time": 1.0}])
    with pytest.raises(InputError, match="no step"):
        read_curve(run)
    with pytest.raises(InputError, match=r"metrics\.jsonl"):
        read_curve(tmp_path / "missing")


def test_the_figure_is_written(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    run = _log(
        tmp_path / "c",
        [{"event": "start", "step": 0, "time": 0.0}]
        + [{"event": "step", "step": k, "loss": 1.0 / k, "time": 6.0 * k} for k in range(1, 30)],
    )
    png = write_learning_curves([read_curve(run)], tmp_path / "fig" / "c.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((tmp_path / "fig").glob("*.tmp*"))


def test_a_run_without_validation_draws_no_empty_legend(tmp_path: Path) -> None:
    """A log with steps and no validation leaves the recall axis without artists: asking it
    for a legend made matplotlib warn "No artists with labels"; the figure says so instead."""
    pytest.importorskip("matplotlib")
    import warnings

    run = _log(
        tmp_path / "c",
        [{"event": "start", "step": 0, "time": 0.0}]
        + [{"event": "step", "step": k, "loss": 1.0 / k, "time": 6.0 * k} for k in range(1, 5)],
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        png = write_learning_curves([read_curve(run)], tmp_path / "c.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
