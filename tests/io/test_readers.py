"""Readers: every format written by an independent route, read back value for value."""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.io.readers import READERS, read_points, reader_for

# A few points with values that are exact in float32 and not symmetric in x, y, z.
XYZ = [(1.5, -2.25, 0.125), (-10.0, 3.75, -1.5), (0.0, 0.5, 7.0), (100.25, -0.75, 2.0)]


def _benchmark_values() -> list[tuple[float, float, float]]:
    """4096 points of a centred, normalised-looking submap, from a plain loop."""
    pts = []
    for i in range(4096):
        a = i * 0.0123
        pts.append((0.6 * ((i % 64) / 63.0 - 0.5), 0.5 * np.sin(a), 0.4 * np.cos(3 * a)))
    return pts


def _pack(path: Path, fmt: str, rows: list[tuple]) -> Path:
    with open(path, "wb") as fh:
        for row in rows:
            fh.write(struct.pack(fmt, *row))
    return path


# --- raw .bin formats ------------------------------------------------------------------------


def test_benchmark_bin_is_read_without_a_reader_name(tmp_path: Path) -> None:
    rows = _benchmark_values()
    path = _pack(tmp_path / "submap.bin", "<3d", rows)
    assert path.stat().st_size == 98_304
    pts = read_points(path)
    assert pts.dtype == np.float64 and pts.shape == (4096, 3)
    assert pts.tolist() == [list(r) for r in rows]
    assert read_points(path, "benchmark").tolist() == pts.tolist()


def test_benchmark_reader_refuses_other_sizes(tmp_path: Path) -> None:
    path = _pack(tmp_path / "short.bin", "<3d", _benchmark_values()[:4095])
    with pytest.raises(InputError, match="exactly 4096") as exc:
        read_points(path, "benchmark")
    assert exc.value.source == str(path)
    # Without a reader name it is not taken for a benchmark submap either.
    with pytest.raises(InputError, match="--reader"):
        read_points(path)


def test_kitti_reader_exact_values_and_drops_reflectance(tmp_path: Path) -> None:
    rows = [(x, y, z, 0.25 * i) for i, (x, y, z) in enumerate(XYZ)]
    path = _pack(tmp_path / "000000.bin", "<4f", rows)
    pts = read_points(path, "kitti")
    assert pts.dtype == np.float32 and pts.shape == (4, 3)
    assert pts.tolist() == [list(r) for r in XYZ]


def test_nuscenes_reader_exact_values(tmp_path: Path) -> None:
    rows = [(x, y, z, 17.0, float(i)) for i, (x, y, z) in enumerate(XYZ)]
    path = _pack(tmp_path / "sweep.bin", "<5f", rows)
    pts = read_points(path, "nuscenes")
    assert pts.dtype == np.float32
    assert pts.tolist() == [list(r) for r in XYZ]


def test_nclt_reader_decodes_scaled_uint16(tmp_path: Path) -> None:
    raw = [(0, 65535, 20000, 7, 31), (20001, 19999, 12345, 255, 0), (40000, 1, 2, 0, 3)]
    path = _pack(tmp_path / "123.bin", "<HHHBB", raw)
    pts = read_points(path, "nclt")
    expected = [[v * 0.005 - 100 for v in r[:3]] for r in raw]
    assert pts.dtype == np.float64
    assert pts.tolist() == expected
    assert pts[0].tolist() == [-100.0, 227.675, 0.0]


def test_nclt_sized_98304_bytes_is_not_taken_for_a_benchmark_submap(tmp_path: Path) -> None:
    # 12,288 NCLT records are 98,304 bytes and read as float64 they are all tiny values in
    # [-1, 1]: the content check must still refuse to guess.
    raw = [
        (20000 + i % 500, 21000 + i % 300, 20000 + i % 50, i % 256, i % 32) for i in range(12288)
    ]
    path = _pack(tmp_path / "scan.bin", "<HHHBB", raw)
    assert path.stat().st_size == 98_304
    with pytest.raises(InputError, match="benchmark") as exc:
        read_points(path)
    assert "nclt (12,288 points)" in str(exc.value)
    assert read_points(path, "nclt").shape == (12288, 3)


def test_ambiguous_bin_lists_the_readers_that_fit(tmp_path: Path) -> None:
    path = _pack(tmp_path / "x.bin", "<4f", [(1.0, 2.0, 3.0, 0.5)] * 10)  # 160 bytes
    with pytest.raises(InputError) as exc:
        read_points(path)
    msg = str(exc.value)
    assert "--reader kitti|nuscenes|nclt|benchmark" in msg
    assert "kitti (10 points)" in msg and "nuscenes (8 points)" in msg and "nclt (20 points)" in msg


@pytest.mark.parametrize(
    ("reader", "record", "extra"), [("kitti", 16, 4), ("nuscenes", 20, 8), ("nclt", 8, 3)]
)
def test_truncated_bin_is_refused(tmp_path: Path, reader: str, record: int, extra: int) -> None:
    path = tmp_path / "cut.bin"
    path.write_bytes(b"\x00" * (record * 5 + extra))
    with pytest.raises(InputError, match=f"not a multiple of {record} bytes") as exc:
        read_points(path, reader)
    assert exc.value.source == str(path)


def test_empty_and_nonfinite_clouds_are_refused(tmp_path: Path) -> None:
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_points(empty, "kitti")
    nan = _pack(tmp_path / "nan.bin", "<4f", [(1.0, 2.0, 3.0, 0.0), (float("nan"), 0, 0, 0)])
    with pytest.raises(InputError, match="1 of 2 points have NaN") as exc:
        read_points(nan, "kitti")
    assert exc.value.source == str(nan)
    inf = tmp_path / "inf.npy"
    np.save(inf, np.array([[0.0, np.inf, 1.0]]))
    with pytest.raises(InputError, match="infinite"):
        read_points(inf)


def test_unknown_reader_suffix_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "cloud.xyz"
    path.write_text("1 2 3\n")
    with pytest.raises(InputError, match=r"unknown point-cloud suffix '\.xyz'"):
        read_points(path)
    with pytest.raises(InputError, match="unknown reader 'velodyne'"):
        read_points(path, "velodyne")
    with pytest.raises(FileNotFoundError):
        read_points(tmp_path / "nope.bin", "kitti")


def test_table_names_and_suffixes() -> None:
    assert set(READERS) == {"benchmark", "kitti", "nuscenes", "nclt", "npy", "pcd", "ply", "las"}
    assert reader_for("a.PCD").name == "pcd"
    assert reader_for("a.laz").name == "las"
    assert reader_for("a.las").name == "las"
    assert reader_for("a.npy").name == "npy"


# --- .npy, .pcd, .ply, .las ------------------------------------------------------------------


def test_npy_first_three_columns_and_dtypes(tmp_path: Path) -> None:
    arr = np.array([[*p, 9.0, 8.0] for p in XYZ], dtype=np.float32)
    np.save(tmp_path / "a.npy", arr)
    pts = read_points(tmp_path / "a.npy")
    assert pts.dtype == np.float32 and pts.flags.c_contiguous
    assert pts.tolist() == [list(p) for p in XYZ]
    np.save(tmp_path / "i.npy", np.array([[1, 2, 3], [4, 5, 6]], dtype=np.int16))
    ints = read_points(tmp_path / "i.npy")
    assert ints.dtype == np.float64 and ints.tolist() == [[1, 2, 3], [4, 5, 6]]


def test_npy_bad_shapes_and_pickles_are_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "flat.npy", np.zeros(12))
    with pytest.raises(InputError, match="at least 3 columns"):
        read_points(tmp_path / "flat.npy")
    np.save(tmp_path / "two.npy", np.zeros((5, 2)))
    with pytest.raises(InputError, match="at least 3 columns"):
        read_points(tmp_path / "two.npy")
    np.save(tmp_path / "obj.npy", np.array([[{"a": 1}, 2, 3]], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="never loaded"):
        read_points(tmp_path / "obj.npy")


def test_pcd_ascii_written_by_hand(tmp_path: Path) -> None:
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS x y z intensity",
        "SIZE 4 4 4 4",
        "TYPE F F F F",
        "COUNT 1 1 1 1",
        f"WIDTH {len(XYZ)}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {len(XYZ)}",
        "DATA ascii",
        *[f"{x} {y} {z} 42" for x, y, z in XYZ],
    ]
    path = tmp_path / "cloud.pcd"
    path.write_text("\n".join(lines) + "\n")
    pts = read_points(path)
    assert pts.shape == (4, 3) and pts.dtype == np.float32
    assert pts.tolist() == [list(p) for p in XYZ]


def test_pcd_binary_written_by_hand(tmp_path: Path) -> None:
    header = (
        "VERSION 0.7\nFIELDS x y z label\nSIZE 8 8 8 1\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(XYZ)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(XYZ)}\nDATA binary\n"
    )
    body = b"".join(struct.pack("<3dB", x, y, z, 7) for x, y, z in XYZ)
    path = tmp_path / "cloud_bin.pcd"
    path.write_bytes(header.encode() + body)
    pts = read_points(path)
    assert pts.dtype == np.float64
    assert pts.tolist() == [list(p) for p in XYZ]


def test_pcd_without_z_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "flat.pcd"
    path.write_text(
        "VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2\n"
    )
    with pytest.raises(InputError, match="no field"):
        read_points(path)


def test_ply_ascii_written_by_hand(tmp_path: Path) -> None:
    header = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(XYZ)}",
        "property double x",
        "property double y",
        "property double z",
        "property uchar red",
        "element face 0",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    path = tmp_path / "cloud.ply"
    path.write_text("\n".join(header + [f"{x} {y} {z} 200" for x, y, z in XYZ]) + "\n")
    pts = read_points(path)
    assert pts.dtype == np.float64
    assert pts.tolist() == [list(p) for p in XYZ]


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_scaled_coordinates(tmp_path: Path, suffix: str) -> None:
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.001])
    header.offsets = np.array([620000.0, 5735000.0, 50.0])
    las = laspy.LasData(header)
    ints = [(12, -7, 1500), (-250, 400, -2), (99999, 3, 0)]
    las.X = np.array([r[0] for r in ints], dtype=np.int32)
    las.Y = np.array([r[1] for r in ints], dtype=np.int32)
    las.Z = np.array([r[2] for r in ints], dtype=np.int32)
    path = tmp_path / f"tile{suffix}"
    las.write(str(path))
    pts = read_points(path)
    expected = [[620000.0 + x * 0.01, 5735000.0 + y * 0.01, 50.0 + z * 0.001] for x, y, z in ints]
    assert pts.dtype == np.float64
    np.testing.assert_allclose(pts, expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("module", "suffix", "content"),
    [("plyfile", ".ply", "ply\n"), ("pypcd4", ".pcd", "VERSION 0.7\n"), ("laspy", ".las", "x")],
)
def test_missing_io_package_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, module: str, suffix: str, content: str
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # makes `import module` fail
    path = tmp_path / f"c{suffix}"
    path.write_text(content)
    with pytest.raises(MissingDependencyError, match=r"pip install 'pnvlad\[io\]'") as exc:
        read_points(path)
    assert module in str(exc.value)


# --- real scans ------------------------------------------------------------------------------

# Point counts and sensor ranges, no pose needed: the two KITTI files are real HDL-64E scans of
# unknown frames (not frames 0 and 5 of sequence 00; the data README).
REAL = [
    ("kitti00_000000.bin", "kitti", 124_668),
    ("kitti00_000005.bin", "kitti", 123_924),
    ("nuscenes_lidar_top.bin", "nuscenes", 34_688),
    ("nclt_1326652795280148.bin", "nclt", 23_546),
]


@pytest.mark.real_scans
@pytest.mark.parametrize(("name", "reader", "count"), REAL)
def test_real_scans_counts_and_ranges(real_scans: Path, name: str, reader: str, count: int) -> None:
    pts = read_points(real_scans / name, reader)
    assert pts.shape == (count, 3)
    horizontal = np.hypot(pts[:, 0], pts[:, 1])
    assert horizontal.max() < 150.0  # sensor ranges are about 100-120 m
    assert np.median(horizontal) < 30.0
    assert np.abs(pts[:, 2]).max() < 30.0
    # The ground is 0-2 m from the origin: most points are within a few metres of z = 0.
    assert np.mean(np.abs(pts[:, 2]) < 3.0) > 0.7
    with pytest.raises(InputError, match="--reader"):
        read_points(real_scans / name)  # a raw scan is never guessed


@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".las", ".laz", ".npy"])
def test_garbage_files_give_a_short_input_error(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"junk{suffix}"
    path.write_text("garbage\nmore garbage\n")
    with pytest.raises(InputError) as exc:
        read_points(path)
    assert exc.value.source == str(path)
    assert "\n" not in str(exc.value)
