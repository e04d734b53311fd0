"""The odometry's steps are not lengthened by facade glass (mapping.edges' odometry
registration).

A real sensor's rays through a window return from behind the glass (the simulator: 30 % of
them, 0.1 to 0.6 m deeper along the ray), so a window lies deeper the more squarely it is seen
and its apparent place turns with the view. Registered on the verification's 1 m voxels, two
keyframes 5 m apart along a glazed street came out about 1 cm longer than the drive, every
step; the odometry's own registration (the keyframes' resolution) must not.

The same scans are cast twice, with the demo sensor's glass and without it (every other draw
the same: the simulator draws the glass's numbers either way), so the difference of each
step's error isolates what the glass does from the rest of the step's error.
"""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.data.accumulate import accumulate
from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.mapping.edges import MAPPING_VERIFY, ODOMETRY_REGISTRATION
from pnvlad_service.preprocess.filter_g import apply_g, scan_config
from pnvlad_service.synth.generate import simulated_drive
from pnvlad_service.synth.presets import get_preset

#: The demo city's first run: its first 25 steps of 5 m (a business street of glazed
#: facades; every other scan of the run is a keyframe).
STEPS = 25


def _keyframes(glass: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each keyframe as ``pnvlad synth`` makes it (the scan laid in UTM axes at its recorded
    position, then G for one scan), in metres, and its true frame pose (float64 [4, 4])."""
    drive = simulated_drive(get_preset("demo"), 0, 0, 0)
    if not glass:
        drive.lidar = drive.lidar.model_copy(update={"glass_loss": 0.0})
    assert drive.lidar.glass_loss == (0.7 if glass else 0.0)
    clouds, truth = [], []
    for i in range(0, 2 * (STEPS + 1), 2):
        local = accumulate(drive.poses, {i: drive.scan(i)}, [i], drive.poses[i, :3, 3])
        g = apply_g(local, scan_config(), seed=i)
        clouds.append(g.centre + g.scale * g.points)
        # a frame point q (recorded axes) truly lies at R_true R_rec^T q + true position
        pose = np.eye(4)
        pose[:3, :3] = drive.true_poses[i, :3, :3] @ drive.poses[i, :3, :3].T
        pose[:3, 3] = drive.true_poses[i, :3, 3]
        truth.append(pose)
    return clouds, truth


def _along_errors(clouds: list[np.ndarray], truth: list[np.ndarray], config) -> np.ndarray:
    """Each step registered as the odometry registers it (from a start 0.3 m and 0.3 m off),
    its error along the true step, metres."""
    prepared = [reg.prepare(c, config, "both") for c in clouds]
    out = []
    for k in range(1, len(clouds)):
        true = np.linalg.inv(truth[k - 1]) @ truth[k]
        start = true.copy()
        start[:2, 3] += 0.3
        r = reg.register(prepared[k], prepared[k - 1], config, init=start)
        along = true[:2, 3] / np.linalg.norm(true[:2, 3])
        out.append(float((r.transform[:2, 3] - true[:2, 3]) @ along))
    return np.array(out)


@pytest.fixture(scope="module")
def scans() -> dict[bool, tuple[list[np.ndarray], list[np.ndarray]]]:
    return {glass: _keyframes(glass) for glass in (True, False)}


@pytest.mark.slow
def test_glass_does_not_lengthen_the_odometry(scans) -> None:
    glazed = _along_errors(*scans[True], ODOMETRY_REGISTRATION)
    clear = _along_errors(*scans[False], ODOMETRY_REGISTRATION)
    lengthened = float(np.median(glazed - clear))
    assert abs(lengthened) < 0.004, f"glass lengthens each step by {lengthened * 1000:.1f} mm"
    # and the steps stay as precise as without glass
    assert np.median(np.abs(glazed)) < 1.5 * np.median(np.abs(clear)) + 0.005


@pytest.mark.slow
def test_the_verifications_grid_would_be_lengthened(scans) -> None:
    """The same check fails on the registration the odometry used before (the verification's
    1 m voxels): this test can tell the bias."""
    config = MAPPING_VERIFY.registration
    glazed = _along_errors(*scans[True], config)
    clear = _along_errors(*scans[False], config)
    assert float(np.median(glazed - clear)) > 0.006


def test_the_odometrys_clouds_skip_the_yaw_search() -> None:
    """Prepared without the yaw search's spectra (the odometry starts every step from the
    recorded one), a cloud registers from a given start exactly as with them, and refuses to
    register without one."""
    rng = np.random.default_rng(0)
    walls = [
        np.c_[rng.uniform(-30, 30, 3000), np.full(3000, 8.0), rng.uniform(0, 10, 3000)],
        np.c_[rng.uniform(-30, 30, 3000), np.full(3000, -8.0), rng.uniform(0, 10, 3000)],
        np.c_[np.full(1500, 30.0), rng.uniform(-8, 8, 1500), rng.uniform(0, 10, 1500)],
        np.c_[
            rng.uniform(-0.2, 0.2, 300) + 5, rng.uniform(-0.2, 0.2, 300) + 6, rng.uniform(0, 5, 300)
        ],
    ]
    world = np.concatenate(walls)
    a, b = world, world - [1.0, 0.0, 0.0]
    start = np.eye(4)
    start[:2, 3] = [0.7, 0.2]
    config = ODOMETRY_REGISTRATION
    plain = [reg.prepare(c, config, "both", search=False) for c in (b, a)]
    full = [reg.prepare(c, config, "both") for c in (b, a)]
    assert plain[0].spectrum is None and plain[0].polar is None
    assert full[0].spectrum is not None
    r_plain = reg.register(*plain, config, init=start)
    r_full = reg.register(*full, config, init=start)
    np.testing.assert_array_equal(r_plain.transform, r_full.transform)
    np.testing.assert_allclose(r_plain.transform[:3, 3], [1.0, 0.0, 0.0], atol=0.02)
    with pytest.raises(ValueError, match="needs an init"):
        reg.register(*plain, config)
