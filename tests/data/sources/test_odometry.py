"""data.sources.odometry: KISS-ICP on real KITTI scans against the sequence's recorded poses,
and the errors a caller can meet (too few points, the extra not installed).

The expected motion is KITTI 00's ground truth, composed with numpy alone (tests/kitti00.py:
P_i = C_i · Tr, scan j in scan i's frame = inv(P_i) · P_j).
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources.odometry import LidarOdometry
from pnvlad_service.errors import InputError
from tests.conftest import REPO
from tests.kitti00 import relative_pose

needs_kiss_icp = pytest.mark.skipif(
    importlib.util.find_spec("kiss_icp") is None, reason="kiss-icp (extra 'odometry') not installed"
)

#: Measured (kiss-icp 1.3.0, default settings): 94 -> 95 off by 0.032 m and 0.030 degrees,
#: 95 -> 94 by 0.022 m and 0.052 degrees. The bounds are about twice the worse of the two.
MAX_TRANSLATION_M = 0.065
MAX_ROTATION_DEG = 0.1


def rotation_deg(r: np.ndarray) -> float:
    """The angle of the rotation ``r`` float64 [3, 3], degrees."""
    return math.degrees(math.acos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


@pytest.fixture(scope="module")
def kitti_scans(real_scans: Path) -> dict[int, np.ndarray]:
    from pnvlad_service.io.readers import read_points

    return {i: read_points(real_scans / f"kitti00_{i:06d}.bin", "kitti") for i in (94, 95)}


@pytest.mark.real_scans
@needs_kiss_icp
@pytest.mark.parametrize(("first", "second"), [(94, 95), (95, 94)])
def test_consecutive_kitti_scans_move_as_recorded(
    real_scans: Path, kitti_scans: dict[int, np.ndarray], first: int, second: int
) -> None:
    odometry = LidarOdometry()
    p0 = odometry.update(kitti_scans[first])
    p1 = odometry.update(kitti_scans[second])
    assert odometry.frames == 2
    # The odometry frame is the first scan's.
    np.testing.assert_allclose(p0, np.eye(4), atol=1e-12)
    assert p1.dtype == np.float64 and p1.shape == (4, 4)
    np.testing.assert_allclose(p1[3], [0, 0, 0, 1])
    expected = relative_pose(real_scans, first, second)
    moved = np.linalg.inv(p0) @ p1
    assert np.linalg.norm(expected[:3, 3]) == pytest.approx(0.47, abs=0.01)  # README's gap
    assert np.linalg.norm(moved[:3, 3] - expected[:3, 3]) < MAX_TRANSLATION_M
    assert rotation_deg(expected[:3, :3].T @ moved[:3, :3]) < MAX_ROTATION_DEG


@needs_kiss_icp
def test_too_few_points_is_an_input_error_and_not_counted() -> None:
    rng = np.random.default_rng(0)
    odometry = LidarOdometry()
    with pytest.raises(InputError) as exc:
        odometry.update(rng.normal(0.0, 10.0, size=(99, 3)))
    assert exc.value.source == "points" and "99 points" in str(exc.value)
    # 150 rows, 60 of them not finite: 90 points left, too few as well.
    pts = rng.normal(0.0, 10.0, size=(150, 4))
    pts[np.arange(60), rng.integers(0, 3, 60)] = np.nan
    with pytest.raises(InputError, match="90 points"):
        odometry.update(pts)
    assert odometry.frames == 0


@needs_kiss_icp
@pytest.mark.parametrize(
    "kwargs", [{"max_range": 0.0}, {"min_range": 5.0, "max_range": 5.0}, {"min_range": -1.0}]
)
def test_bad_ranges_are_input_errors(kwargs: dict) -> None:
    with pytest.raises(InputError) as exc:
        LidarOdometry(**kwargs)
    assert exc.value.source == "range"


def test_without_kiss_icp_the_error_names_the_extra() -> None:
    # A fresh interpreter in which `import kiss_icp` fails (a None entry in sys.modules).
    code = (
        "import sys; sys.modules['kiss_icp'] = None\n"
        "from pnvlad_service.data.sources.odometry import LidarOdometry\n"
        "from pnvlad_service.errors import MissingDependencyError\n"
        "try:\n"
        "    LidarOdometry()\n"
        "except MissingDependencyError as e:\n"
        "    print(e)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == (
        "LiDAR odometry (accumulated queries) needs the 'kiss-icp' package, which is not "
        "installed. Install it with: pip install 'pnvlad[odometry]'"
    )


def test_the_odometry_extra_is_declared() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    assert any(req.replace(" ", "").startswith("kiss-icp>=") for req in extras["odometry"])
    dev = [r for r in extras["dev"] if r.startswith("pnvlad[")]
    assert "odometry" in dev[0].removeprefix("pnvlad[").removesuffix("]").split(",")
