"""fileio: the one file hash, against hashlib over the whole file at once."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from pnvlad_service.fileio import sha256_file


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
