"""io.submap: the one reader and writer of the benchmark's .bin, checked against struct."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_points
from pnvlad_service.io.submap import (
    SUBMAP_BYTES,
    SUBMAP_POINTS,
    read_bin_points,
    read_submap,
    write_submap,
)

# A few points with values that are exact in float32 and not symmetric in x, y, z.
XYZ = [(1.5, -2.25, 0.125), (-10.0, 3.75, -1.5), (0.0, 0.5, 7.0), (100.25, -0.75, 2.0)]


def _submap_rows() -> list[tuple[float, float, float]]:
    """4096 points of a centred, normalised-looking submap, from a plain loop."""
    return [
        (0.6 * ((i % 64) / 63.0 - 0.5), 0.5 * np.sin(i * 0.0123), 0.4 * np.cos(3 * i * 0.0123))
        for i in range(4096)
    ]


def _pack(path: Path, rows: list[tuple[float, float, float]]) -> Path:
    path.write_bytes(b"".join(struct.pack("<3d", *r) for r in rows))
    return path


def test_constants_describe_98304_bytes() -> None:
    assert SUBMAP_POINTS == 4096
    assert SUBMAP_BYTES == 98_304 == len(struct.pack("<3d", 0, 0, 0)) * 4096


# --- read_submap -----------------------------------------------------------------------------


def test_read_submap_reads_the_struct_packed_values(tmp_path: Path) -> None:
    rows = _submap_rows()
    pts = read_submap(_pack(tmp_path / "s.bin", rows))
    assert pts.shape == (4096, 3) and pts.dtype == np.float64
    assert pts.tolist() == [list(r) for r in rows]


@pytest.mark.parametrize("points", [4095, 4097, 1])
def test_read_submap_refuses_other_sizes_naming_the_file(tmp_path: Path, points: int) -> None:
    path = _pack(tmp_path / "odd.bin", _submap_rows()[:1] * points)
    with pytest.raises(InputError, match="exactly 4096 float64 points") as exc:
        read_submap(path)
    assert exc.value.source == str(path)
    assert f"this file has {points * 24:,} bytes" in str(exc.value)


def test_read_submap_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_submap(tmp_path / "none.bin")


def test_read_bin_points_takes_any_count_of_triples(tmp_path: Path) -> None:
    path = _pack(tmp_path / "s.bin", XYZ)
    assert read_bin_points(path).tolist() == [list(r) for r in XYZ]
    path.write_bytes(path.read_bytes() + struct.pack("<d", 1.0))  # 13 float64 values
    with pytest.raises(InputError, match="13 float64 values, not a multiple of 3") as exc:
        read_bin_points(path)
    assert exc.value.source == str(path)


# --- write_submap ----------------------------------------------------------------------------


def test_write_submap_bin_bytes_and_round_trip(tmp_path: Path) -> None:
    rows = _submap_rows()
    path = tmp_path / "out" / "submap.bin"
    write_submap(path, np.array(rows, dtype=np.float32).astype(np.float64))
    expected = b"".join(struct.pack("<3d", *r) for r in np.array(rows, np.float32).tolist())
    assert path.read_bytes() == expected
    assert len(expected) == 98_304
    assert read_points(path).tolist() == np.array(rows, np.float32).astype(float).tolist()
    assert [p.name for p in path.parent.iterdir()] == ["submap.bin"]  # no temporary left


def test_write_then_read_submap_round_trip_is_exact(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).uniform(-1, 1, (SUBMAP_POINTS, 3))
    write_submap(tmp_path / "s.bin", pts)
    back = read_submap(tmp_path / "s.bin")
    assert back.dtype == np.float64 and np.array_equal(back, pts)


def test_write_submap_npy_round_trip(tmp_path: Path) -> None:
    pts = np.array(XYZ, dtype=np.float32)
    write_submap(tmp_path / "s.npy", pts)
    back = np.load(tmp_path / "s.npy")
    assert back.dtype == np.float64 and back.tolist() == [list(p) for p in XYZ]


def test_write_submap_refuses_bad_input_and_leaves_old_file(tmp_path: Path) -> None:
    path = tmp_path / "s.bin"
    path.write_bytes(b"old")
    with pytest.raises(InputError, match="NaN"):
        write_submap(path, np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(InputError, match=r"shape \[N, 3\]"):
        write_submap(path, np.zeros((4, 2)))
    with pytest.raises(InputError, match=r"\.bin or \.npy"):
        write_submap(tmp_path / "s.txt", np.zeros((4, 3)))
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.bin"]
