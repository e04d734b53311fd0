"""benchmarks/submap_extent.py: the extent of hand-made clouds, and the script end to end on a
tiny synthetic tree (its windows laid again exactly as prepare laid them)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.benchmark_scripts import BENCHMARKS, load


@pytest.fixture(scope="module")
def se():  # the script as a module
    return load("submap_extent")


@pytest.mark.parametrize("turn_deg", [0.0, 30.0, 77.0])
def test_a_turned_slab_measures_its_sides_and_height(se, turn_deg: float) -> None:
    rng = np.random.default_rng(1)
    # 40 m x 10 m x 6 m, its corners included so that max - min is exact, turned about z.
    box = rng.uniform([-20, -5, 0], [20, 5, 6], size=(20_000, 3))
    corners = np.array([[x, y, z] for x in (-20, 20) for y in (-5, 5) for z in (0, 6)], float)
    pts = np.vstack([box, corners])
    a = math.radians(turn_deg)
    turn = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    e = se.extent(pts @ turn.T + [620_000.0, 5_735_000.0, 50.0])
    # The 1-degree search finds the slab's own axes (turns chosen on the grid): exact sides.
    assert e.long == pytest.approx(40.0, abs=1e-6)
    assert e.short == pytest.approx(10.0, abs=1e-6)
    assert e.height == pytest.approx(6.0, abs=1e-9)
    # The turned slab's bounding box in x, y: 40 cos a + 10 sin a by 40 sin a + 10 cos a.
    xy = (40 * math.cos(a) + 10 * math.sin(a), 40 * math.sin(a) + 10 * math.cos(a))
    assert e.xy == pytest.approx(xy, abs=1e-6)
    # Uniform points: 90 % of each side between the 5th and 95th percentiles.
    assert e.robust == pytest.approx((36.0, 9.0, 5.4), rel=0.02)


def test_a_stray_return_moves_max_min_but_not_the_percentiles(se) -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform([-10, -10, 0], [10, 10, 3], size=(5000, 3))
    far = np.vstack([pts, [[80.0, 0.0, 1.0]]])
    a, b = se.extent(pts), se.extent(far)
    assert b.long > 80 and a.long < 21
    assert b.robust == pytest.approx(a.robust, rel=0.02)


def test_box_cut_and_the_table(se) -> None:
    pts = np.array([[0.0, 0, 0], [14.9, -14.9, 1], [15.1, 0, 2], [0, -15.2, 3]])
    np.testing.assert_array_equal(se.box_cut(pts, 30.0), pts[:2])
    e = se.extent(np.random.default_rng(0).uniform(-1, 1, (100, 3)))
    row = se.Row("hand-made", [e, e], [e, e], [100, 300], [2.0, 4.0])
    text = se.table([row])
    assert text.splitlines()[2].startswith("| hand-made | 2 | 200 |")
    assert "| 3.0 [2.1-3.9] |" in text  # the scales' median and 5th-95th percentiles
    with pytest.raises(Exception, match="finite non-empty"):
        se.extent(np.empty((0, 3)))


def test_the_script_on_a_tree_relays_prepares_windows(tiny: Path) -> None:
    done = subprocess.run(
        [
            sys.executable,
            str(BENCHMARKS / "submap_extent.py"),
            "--tree",
            str(tiny),
            "--samples",
            "3",
            "--box",
            "1000",
            "--no-real",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    own, wide = (line.split("|")[2:] for line in lines[2:4])
    # A 1 km box cuts nothing: the same windows, and G run again on them gives the tree's own
    # submaps (the same seed and settings as prepare), so every column agrees.
    assert own == wide
    assert lines[2].startswith("| tiny | 3 |")
    bad = subprocess.run(
        [sys.executable, str(BENCHMARKS / "submap_extent.py"), "--box", "-3", "--no-real"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "positive number of metres" in bad.stderr
