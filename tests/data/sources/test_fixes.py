"""Position fixes: the fit of an odometry onto them recovers a known placement, the files a
run keeps round-trip, latitude/longitude fixes land where PROJ's inverse says, fixes that jump
are refused by name, and prepare keeps the fixes of a fix-only drive (and drops stale ones)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources.fix_odometry import fit_to_fixes, fix_steps
from pnvlad_service.data.sources.fixes import (
    FIXES_CSV,
    Fixes,
    check_jumps,
    read_fixes_csv,
    read_run_fixes,
    write_run_fixes,
)
from pnvlad_service.errors import InputError


def _path(n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """A drive at 10 m/s, one pose a metre, turning gently: stamps µs, true poses [n, 4, 4]."""
    s = np.arange(n, dtype=np.float64)
    yaw = 0.004 * s + 0.3 * np.sin(s / 80.0)
    step = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    xy = np.cumsum(step, axis=0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 0], poses[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    poses[:, 1, 0], poses[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    poses[:, :2, 3] = xy + np.array([620000.0, 5735000.0])
    poses[:, 2, 3] = 40.0
    return (1_000_000 + s * 100_000).astype(np.int64), poses


def _in_odometry_frame(poses: np.ndarray, yaw: float, shift: np.ndarray) -> np.ndarray:
    """The same poses seen from another frame (turned by ``yaw`` about up, shifted)."""
    place = np.eye(4)
    place[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    place[:3, 3] = shift
    return np.linalg.inv(place) @ poses


def test_the_fit_lays_an_odometry_onto_exact_fixes_where_it_truly_is() -> None:
    stamps, truth = _path()
    odo = _in_odometry_frame(truth, 1.1, np.array([619000.0, 5736000.0, 3.0]))
    idx = np.arange(0, len(stamps), 10)  # one fix a second
    fixes = Fixes(stamps[idx], truth[idx, :3, 3].copy(), np.full(len(idx), np.nan))
    laid = fit_to_fixes(stamps, odo, fixes)
    assert np.abs(laid[:, :3, 3] - truth[:, :3, 3]).max() < 1e-6
    assert np.abs(laid[:, :3, :3] - truth[:, :3, :3]).max() < 1e-9


def test_the_fit_averages_the_fixes_noise_and_follows_a_slow_drift() -> None:
    stamps, truth = _path()
    rng = np.random.default_rng(0)
    odo = _in_odometry_frame(truth, -0.4, np.zeros(3))
    # the odometry turns 0.01 degree a metre too far: 4 degrees over the drive
    a = math.radians(0.01)
    turn = np.eye(4)
    turn[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    drift = np.tile(np.eye(4), (len(odo), 1, 1))
    for k in range(1, len(odo)):
        drift[k] = drift[k - 1] @ turn @ np.linalg.inv(odo[k - 1]) @ odo[k]
    idx = np.arange(0, len(stamps), 10)
    noise = rng.normal(0.0, 1.0, (len(idx), 3)) * [1.0, 1.0, 0.0]
    fixes = Fixes(stamps[idx], truth[idx, :3, 3] + noise, np.full(len(idx), 1.0))
    laid = fit_to_fixes(stamps, drift, fixes)
    err = np.linalg.norm(laid[:, :2, 3] - truth[:, :2, 3], axis=1)
    raw = np.linalg.norm(noise[:, :2], axis=1)
    assert np.median(err) < 0.5 * np.median(raw) and err.max() < 1.5
    # with no fit, that drift alone would leave the drive's end metres off
    whole = fit_to_fixes(stamps, drift, fixes, window_m=1e6)
    assert np.linalg.norm(whole[-1, :2, 3] - truth[-1, :2, 3]) > 2 * err[-1]


def test_fixes_that_do_not_overlap_the_scans_are_refused_by_name() -> None:
    stamps, truth = _path()
    fixes = Fixes(stamps[:3] - 10**9, truth[:3, :3, 3].copy(), np.full(3, np.nan))
    with pytest.raises(InputError, match="do not overlap") as err:
        fit_to_fixes(stamps, truth, fixes, name="city/run7")
    assert "city/run7" in str(err.value)


def test_a_fix_that_jumps_is_refused_with_the_run_and_its_time() -> None:
    stamps, truth = _path()
    idx = np.arange(0, len(stamps), 10)
    enu = truth[idx, :3, 3].copy()
    enu[20:, 0] += 12.0  # a receiver that jumps 12 m and stays there
    fixes = Fixes(stamps[idx], enu, np.full(len(idx), np.nan))
    with pytest.raises(InputError, match=r"jump 12\.0 m") as err:
        check_jumps(fixes, truth[idx, :3, 3], "city/run7")
    assert "city/run7" in str(err.value) and str(stamps[idx[20]]) in str(err.value)
    check_jumps(fixes, enu, "city/run7")  # against an odometry that jumps with them: none


def test_the_speed_of_the_fixes_gives_each_scan_its_step() -> None:
    stamps, truth = _path()
    idx = np.arange(0, len(stamps), 10)
    fixes = Fixes(stamps[idx], truth[idx, :3, 3].copy(), np.full(len(idx), np.nan))
    steps = fix_steps(stamps, fixes)
    assert steps[0] == 0.0
    assert np.abs(steps[1:] - 1.0).max() < 0.02  # 1 m a scan, less the curve's chord


def test_a_runs_fixes_round_trip_and_mark_it(tmp_path: Path) -> None:
    stamps, truth = _path(50)
    fixes = Fixes(stamps, truth[:, :3, 3].copy(), np.r_[np.full(25, np.nan), np.full(25, 2.0)])
    laid = truth[:, :3, 3] + 0.5
    assert read_run_fixes(tmp_path) is None
    write_run_fixes(tmp_path, fixes, laid)
    back, back_laid = read_run_fixes(tmp_path)  # type: ignore[misc]
    assert np.array_equal(back.stamps, stamps) and np.array_equal(back.enu, fixes.enu)
    assert np.array_equal(back_laid, laid)
    assert np.isnan(back.std_m[:25]).all() and (back.std_m[25:] == 2.0).all()


def test_latitude_longitude_fixes_land_where_the_inverse_says(tmp_path: Path) -> None:
    pytest.importorskip("pyproj")
    from pnvlad_service.io.utm import to_latlon

    east = np.array([620000.0, 620010.0, 620020.5])
    north = np.array([5735000.0, 5735003.0, 5735007.25])
    lat, lon = to_latlon("30U", east, north)
    csv = tmp_path / "fixes.csv"
    rows = [
        f"{t},{float(a)!r},{float(o)!r},12.5" for t, a, o in zip((1, 2, 3), lat, lon, strict=True)
    ]
    csv.write_text("timestamp,latitude,longitude,altitude\n" + "\n".join(rows) + "\n")
    fixes = read_fixes_csv(csv, "30U")
    assert np.abs(fixes.enu[:, 0] - east).max() < 1e-6
    assert np.abs(fixes.enu[:, 1] - north).max() < 1e-6
    assert (fixes.enu[:, 2] == 12.5).all()
    with pytest.raises(InputError, match="--utm-zone"):
        read_fixes_csv(csv)


def test_prepare_keeps_a_fix_drives_fixes_and_drops_stale_ones(tmp_path: Path) -> None:
    from pnvlad_service.data.prepare import keep_fixes

    stamps, truth = _path(30)
    fixes = Fixes(stamps, truth[:, :3, 3].copy(), np.full(30, np.nan))

    class Laid:
        def __init__(self) -> None:
            self.fixes, self.laid_at_fixes = fixes, truth[:, :3, 3]

    keep_fixes(Laid(), tmp_path)  # type: ignore[arg-type]
    assert (tmp_path / FIXES_CSV).is_file()
    keep_fixes(object(), tmp_path)  # type: ignore[arg-type]
    assert not (tmp_path / FIXES_CSV).exists()
