"""fileio: the one file hash, against hashlib over the whole file at once; report rows as CSV."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path
from types import SimpleNamespace

import pytest

from pnvlad_service.fileio import atomic_write_rows, sha256_file


@pytest.mark.parametrize("chunk", [1, 7, 1 << 22])
def test_sha256_file_matches_hashlib_whatever_the_chunk(tmp_path: Path, chunk: int) -> None:
    data = bytes(range(256)) * 41 + b"tail"
    path = tmp_path / "blob.bin"
    path.write_bytes(data)
    assert sha256_file(path, chunk=chunk) == hashlib.sha256(data).hexdigest()
    assert sha256_file(str(path)) == hashlib.sha256(data).hexdigest()


def test_sha256_file_of_an_empty_file(tmp_path: Path) -> None:
    (tmp_path / "empty").write_bytes(b"")
    assert sha256_file(tmp_path / "empty") == hashlib.sha256(b"").hexdigest()


def test_rows_round_trip_through_a_csv_reader(tmp_path: Path) -> None:
    rows = [
        SimpleNamespace(scan=0, ok=True, error=0.1 + 0.2, pose=None),
        SimpleNamespace(scan=1, ok=False, error=2.0 / 3.0, pose="a,b"),
    ]
    path = atomic_write_rows(rows, ["scan", "ok", "error", "pose"], tmp_path / "r.csv")
    got = list(csv.DictReader(path.open(newline="")))
    assert got == [
        {"scan": "0", "ok": "true", "error": "0.30000000000000004", "pose": ""},
        {"scan": "1", "ok": "false", "error": repr(2.0 / 3.0), "pose": "a,b"},
    ]
    rounded = atomic_write_rows(rows, ["error"], tmp_path / "d.csv", digits=6)
    assert rounded.read_text().splitlines() == ["error", "0.3", "0.666667"]
    assert not list(tmp_path.glob(".*"))  # nothing left under a temporary name
