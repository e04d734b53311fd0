"""data.sources.csv_drive: a folder of scans plus a pose CSV -> timestamps, UTM poses, scans.

Expectations are hand-worked headings and matrices that must agree.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources.csv_drive import CsvDrive
from pnvlad_service.errors import InputError
from tests.data.helpers import write_street


def test_csv_drive_headings_and_matrices_agree(tmp_path: Path) -> None:
    stamps = [1_000_000 + 100_000 * i for i in range(3)]
    write_street(tmp_path / "scans", stamps, np.random.default_rng(0))
    base = [(ts, 5_735_000.0 + i, 620_000.0 + 2 * i) for i, ts in enumerate(stamps)]
    (tmp_path / "yaw.csv").write_text(
        "timestamp,northing,easting,yaw_deg,height\n"
        + "".join(f"{t},{n},{e},30,1.5\n" for t, n, e in base)
    )
    (tmp_path / "heading.csv").write_text(
        "timestamp,northing,easting,heading_rad\n"
        + "".join(f"{t},{n},{e},{math.radians(60)!r}\n" for t, n, e in base)
    )
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    (tmp_path / "matrix.csv").write_text(
        "timestamp,"
        + ",".join(f"r{r}{k}" for r in range(3) for k in range(4))
        + "\n"
        + "".join(
            f"{t},{c!r},{-s!r},0,{e},{s!r},{c!r},0,{n},0,0,1,0\n" for t, n, e in reversed(base)
        )
    )
    yaw = CsvDrive(tmp_path / "scans", tmp_path / "yaw.csv")
    heading = CsvDrive(tmp_path / "scans", tmp_path / "heading.csv")
    matrix = CsvDrive(tmp_path / "scans", tmp_path / "matrix.csv")
    assert yaw.timestamps.tolist() == stamps == matrix.timestamps.tolist()
    # The sensor's x axis points 30 deg north of east.
    np.testing.assert_allclose(yaw.poses[0, :3, 0], [c, s, 0.0], atol=1e-12)
    np.testing.assert_allclose(yaw.poses[2, :3, 3], [620_004.0, 5_735_002.0, 1.5], atol=1e-6)
    np.testing.assert_allclose(heading.poses[:, :3, :3], yaw.poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(matrix.poses[:, :3, :3], yaw.poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(matrix.poses[:, :2, 3], yaw.poses[:, :2, 3], atol=1e-6)
    assert yaw.scan(1).shape == (3000, 3)


def test_csv_drive_missing_files_and_rows(tmp_path: Path) -> None:
    stamps = [1_000_000, 1_100_000, 1_200_000]
    write_street(tmp_path / "scans", stamps, np.random.default_rng(1))
    poses = tmp_path / "poses.csv"
    rows = "".join(f"{t},{5_735_000 + i},620000,0\n" for i, t in enumerate([*stamps, 1_300_000]))
    poses.write_text("timestamp,northing,easting,yaw_rad\n" + rows)
    with pytest.raises(InputError, match="1300000") as exc:
        CsvDrive(tmp_path / "scans", poses)
    assert exc.value.source == str(poses)
    assert len(CsvDrive(tmp_path / "scans", poses, skip_missing=True)) == 3

    poses.write_text("timestamp,northing,easting,yaw_rad\n" + rows.split("\n", 1)[1])
    (tmp_path / "scans" / "1300000.npy").write_bytes(
        (tmp_path / "scans" / "1000000.npy").read_bytes()
    )
    with pytest.raises(InputError, match=r"1000000\.npy") as exc:
        CsvDrive(tmp_path / "scans", poses)
    assert exc.value.source == str(tmp_path / "scans" / "1000000.npy")

    poses.write_text("timestamp,northing,easting\n1000000,1,2\n")
    with pytest.raises(InputError, match="heading"):
        CsvDrive(tmp_path / "scans", poses)
    poses.write_text("timestamp,northing,easting,yaw_deg\n1000000,nan,2,0\n")
    with pytest.raises(InputError, match="row 2, column northing"):
        CsvDrive(tmp_path / "scans", poses)
