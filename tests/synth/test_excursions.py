"""Drives that leave the map and come back, and kidnapped ones (synth/excursions.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.synth.excursions import Kidnapped, off_map_drive, out_and_back
from pnvlad_service.synth.generate import get_preset, simulated_drive
from pnvlad_service.synth.runs import Route


def straight(length: float) -> Route:
    x = np.arange(0.0, length + 0.5, 1.0)
    return Route(np.c_[x, np.zeros_like(x)], x.copy(), np.full(len(x), 5.0))


def test_out_and_back_turns_round_and_comes_back_the_way_it_went() -> None:
    r = out_and_back(straight(100.0), 80.0, 30.0)
    assert np.allclose(r.points[0], [0.0, 0.0])
    assert r.points[:, 0].max() == pytest.approx(80.0 + 4.0, abs=0.6)  # the half circle's tip
    assert np.allclose(r.points[-1], [30.0, 0.0], atol=0.6)
    # The way back lies on the way out but for the turn and the merge.
    back = r.points[r.s > 80.0 + np.pi * 4.0 + np.hypot(12.0, 8.0) + 1.0]  # turn, merge
    assert np.abs(back[:, 1]).max() < 1e-9
    # Heading changes smoothly: never more than 45 degrees from one metre to the next.
    d = np.diff(r.points, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    assert np.abs(np.diff(yaw)).max() < np.radians(45) and yaw[-1] == pytest.approx(np.pi, abs=0.01)
    with pytest.raises(InputError):
        out_and_back(straight(100.0), 80.0, 75.0)


def test_an_off_map_drive_leaves_the_route_and_comes_back_onto_it() -> None:
    spec = get_preset("tiny")
    plain = simulated_drive(spec, 0, 1, 0)
    off = off_map_drive(spec, 0, 1, 0, out_m=120.0, back_m=60.0)
    assert off.reverse == plain.reverse and off.speed == plain.speed
    route = plain.true_poses[:, :2, 3]
    away = np.array([np.linalg.norm(route - p, axis=1).min() for p in off.true_poses[:, :2, 3]])
    assert away.max() > 40.0  # off the streets the runs drive
    assert away[0] < 1.0 and away[-1] < 10.0  # starts on them, ends on them (the other lane)
    assert len(off) > len(plain) * 0.9


def test_a_kidnapped_drive_drops_the_gap_and_its_odometry_sees_nothing() -> None:
    drive = simulated_drive(get_preset("tiny"), 0, 0, 0)
    t = (drive.timestamps - drive.timestamps[0]) / 1e6
    k = Kidnapped(drive, at_s=5.0, gap_s=8.0)
    kept = np.flatnonzero((t < 5.0) | (t >= 13.0))
    assert np.array_equal(k.index, kept) and len(k) == len(kept)
    g = k.gap_index
    assert t[k.index[g - 1]] < 5.0 <= 13.0 <= t[k.index[g]]
    assert (k.timestamps[g] - k.timestamps[g - 1]) / 1e6 > 8.0
    np.testing.assert_allclose(k.true_poses, drive.true_poses[kept])
    # The odometry: no motion across the gap, the drive's own motion on either side of it.
    np.testing.assert_allclose(np.linalg.inv(k.poses[g - 1]) @ k.poses[g], np.eye(4), atol=1e-9)
    for a, b in ((g - 3, g - 2), (g + 1, g + 2)):
        want = np.linalg.inv(drive.poses[kept[a]]) @ drive.poses[kept[b]]
        np.testing.assert_allclose(np.linalg.inv(k.poses[a]) @ k.poses[b], want, atol=1e-9)
    assert np.array_equal(k.scan(g), drive.scan(int(kept[g])))
    hidden = Kidnapped(drive, at_s=5.0, gap_s=8.0, hide_gap=True)
    steps = np.diff(hidden.timestamps)
    assert steps[g - 1] == int(np.median(np.diff(drive.timestamps)))
    assert (steps > 0).all()
    with pytest.raises(InputError, match="do not hold a gap"):
        Kidnapped(drive, at_s=t[-1] - 1.0, gap_s=30.0)
