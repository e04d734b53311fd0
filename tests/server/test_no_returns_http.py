"""Raw scans with missing returns written as zeros (Ouster's drivers) sent to a real `pnvlad
serve` on 127.0.0.1, as a binary body and as JSON: the zeros are dropped before the filter G
and counted (the answer is the clean scan's, with ``no_returns``), and a cloud with too few
returns left is a 422 naming the field, as is one that is all zeros. `pnvlad localize SCAN
--preprocess` counts them in a log line and refuses an all-zero file in one line naming it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.server.helpers import held_scan

OCTET = {"content-type": "application/octet-stream"}


def _with_zeros(scan: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``scan`` with ``n`` points at the origin (and a centimetre off it, as Ouster's beam
    origins are) scattered among its rows."""
    rng = np.random.default_rng(seed)
    zeros = np.zeros((n, 3), dtype=scan.dtype)
    zeros[::2, 0] = 0.0158  # the beam's origin, 1.6 cm from the axis
    out = np.concatenate([scan, zeros])
    return np.ascontiguousarray(out[rng.permutation(len(out))])


def _ask(url: str, points: np.ndarray, as_json: bool) -> httpx.Response:
    if as_json:
        body = {"points": points.astype(float).tolist(), "preprocess": True, "verify": False}
        return httpx.post(f"{url}/localize", json=body, timeout=60)
    params = {"preprocess": "true", "verify": "false"}
    return httpx.post(f"{url}/localize", params=params, content=points.tobytes(), headers=OCTET,
                      timeout=60)  # fmt: skip


@pytest.mark.parametrize("as_json", [False, True])
def test_zeros_are_dropped_before_the_filter(keys_server: str, tiny_maps: dict, as_json: bool):
    scan = held_scan(tiny_maps)
    clean = _ask(keys_server, scan, as_json)
    dirty = _ask(keys_server, _with_zeros(scan, len(scan) // 3), as_json)
    assert clean.status_code == dirty.status_code == 200, dirty.text
    assert clean.json()["no_returns"] == 0
    assert dirty.json()["no_returns"] == len(scan) // 3  # counted in the answer
    a, b = clean.json()["matches"], dirty.json()["matches"]
    # The filter G is order-free: the cleaned scan is the clean one, so is every distance.
    assert [(m["run"], m["timestamp"]) for m in a] == [(m["run"], m["timestamp"]) for m in b]
    assert [m["distance"] for m in b] == pytest.approx([m["distance"] for m in a], abs=1e-4)


@pytest.mark.parametrize("as_json", [False, True])
@pytest.mark.parametrize("returns", [0, 5])
def test_a_cloud_without_returns_is_a_422(keys_server: str, tiny_maps: dict, as_json: bool,
                                          returns: int) -> None:  # fmt: skip
    pts = _with_zeros(held_scan(tiny_maps)[:returns], 2000)
    r = _ask(keys_server, pts, as_json)
    assert r.status_code == 422, r.text
    doc = r.json()
    assert doc["field"] == ("points" if as_json else "body"), doc
    assert "within 0.1 m of the sensor" in doc["detail"] and "2,000 lie" in doc["detail"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pnvlad_cli.main", "localize", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def test_localize_a_scan_file_counts_and_refuses_zeros(tiny_maps: dict, tmp_path: Path) -> None:
    scan = held_scan(tiny_maps)
    dirty = tmp_path / "dirty.npy"
    np.save(dirty, _with_zeros(scan, 777))
    res = _cli(str(dirty), "--preprocess", "--index", str(tiny_maps["keys"]), "--no-verify")
    assert res.returncode == 0, res.stderr
    assert f"{dirty}: 777 missing returns (points at the sensor's origin) dropped" in res.stderr
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((500, 3), dtype="<f4"))
    res = _cli(str(empty), "--preprocess", "--index", str(tiny_maps["keys"]))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and str(empty) in lines[0] and "without returns" in lines[0], lines
