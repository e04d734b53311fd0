"""Smoothing a map along its drives: the blend against a direct computation, its invariants,
the bundle that records it, adding runs to it, and the commands' options."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.index import build as ib
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.index.manifest import MANIFEST_FILE, MapRecord
from pnvlad_service.index.smoothing import Smoothing, smooth_along_drives
from tests.index.helpers import PER_RUN, RUNS


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _direct(desc, dim, drives, pos, radius, weight) -> np.ndarray:
    """The blend written out entry by entry and heading by heading."""
    out = np.empty_like(desc)
    for i in range(len(desc)):
        near = [
            j
            for j in range(len(desc))
            if j != i and drives[j] == drives[i] and np.hypot(*(pos[j] - pos[i])) <= radius
        ]
        for b in range(0, desc.shape[1], dim):
            own = desc[i, b : b + dim].astype(np.float64)
            if near:
                own = own + weight * np.mean([desc[j, b : b + dim] for j in near], axis=0)
            out[i, b : b + dim] = own / np.linalg.norm(own)
    return out


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 14),
    turns=st.sampled_from([1, 2, 4]),
    radius=st.floats(1.0, 60.0),
    weight=st.floats(0.05, 2.0),
    seed=st.integers(0, 2**16),
)
def test_blend_is_the_mean_of_the_drives_neighbours(n, turns, radius, weight, seed) -> None:
    rng = np.random.default_rng(seed)
    dim = 8
    desc = _unit(rng.normal(size=(n, turns, dim))).reshape(n, turns * dim).astype(np.float32)
    drives = rng.integers(0, 3, n)
    pos = rng.uniform(0, 80, (n, 2))
    got = smooth_along_drives(desc, dim, drives, pos, radius, weight)
    np.testing.assert_allclose(got, _direct(desc, dim, drives, pos, radius, weight), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got.reshape(n, turns, dim), axis=2), 1.0, atol=1e-5)


def test_other_drives_and_far_entries_change_nothing() -> None:
    rng = np.random.default_rng(3)
    desc = _unit(rng.normal(size=(6, 16))).astype(np.float32)
    pos = np.array([[0, 0], [20, 0], [40, 0], [0, 0], [20, 0], [200, 0]], dtype=np.float64)
    drives = np.array(["a", "a", "a", "b", "b", "b"])
    got = smooth_along_drives(desc, 16, drives, pos, 25.0, 0.5)
    other = desc.copy()
    other[3:] = _unit(rng.normal(size=(3, 16)))
    # drive a's entries do not see drive b's, though they lie at the same places
    np.testing.assert_array_equal(
        smooth_along_drives(other, 16, drives, pos, 25.0, 0.5)[:3], got[:3]
    )
    # entry 5 has no neighbour of its drive within 25 m: unchanged
    np.testing.assert_allclose(got[5], desc[5], atol=1e-6)
    # the middle entry of drive a: its own plus half the mean of both neighbours
    np.testing.assert_allclose(got[1], _unit(desc[1] + 0.25 * (desc[0] + desc[2])), atol=1e-6)


def test_a_denser_map_blends_with_the_same_weight() -> None:
    """The mean, not the sum: an entry whose neighbours all look alike gets the same blend
    from one of them as from eight (a map cut every 20 m or every 5 m)."""
    rng = np.random.default_rng(5)
    own, other = _unit(rng.normal(size=(2, 32))).astype(np.float32)
    expected = _unit(own + 0.5 * other)
    for k in (1, 2, 8):
        desc = np.vstack([own, np.repeat(other[None], k, axis=0)])
        pos = np.c_[np.arange(k + 1) * 2.0, np.zeros(k + 1)]
        got = smooth_along_drives(desc, 32, np.zeros(k + 1), pos, 25.0, 0.5)
        np.testing.assert_allclose(got[0], expected, atol=1e-6)


def test_across_drives_every_drive_within_the_radius_blends() -> None:
    rng = np.random.default_rng(4)
    desc = _unit(rng.normal(size=(5, 8))).astype(np.float32)
    pos = np.array([[0, 0], [3, 0], [20, 0], [0, 2], [60, 0]], dtype=np.float64)
    drives = np.array(["a", "a", "a", "b", "b"])
    across = np.zeros(5)
    got = smooth_along_drives(desc, 8, across, pos, 25.0, 0.5)
    np.testing.assert_allclose(got, _direct(desc, 8, across, pos, 25.0, 0.5), atol=1e-6)
    # entry 0 blends drive b's entry 3 (2 m away) too, unlike along its own drive only
    np.testing.assert_allclose(got[0], _unit(desc[0] + 0.5 * desc[[1, 2, 3]].mean(0)), atol=1e-6)
    own = smooth_along_drives(desc, 8, drives, pos, 25.0, 0.5)
    np.testing.assert_allclose(own[0], _unit(desc[0] + 0.5 * desc[[1, 2]].mean(0)), atol=1e-6)


@pytest.mark.parametrize(
    ("radius", "weight", "field"),
    [(0.0, 0.5, "--smooth"), (-3.0, 0.5, "--smooth"), (float("nan"), 0.5, "--smooth"),
     (150.0, 0.5, "--smooth"), (25.0, 0.0, "--smooth-weight"),
     (25.0, float("inf"), "--smooth-weight")],
)  # fmt: skip
def test_impossible_settings_name_their_option(radius, weight, field) -> None:
    with pytest.raises(InputError) as err:
        Smoothing(radius, weight)
    assert err.value.source == field


def test_the_manifest_round_trips_and_refuses_a_malformed_entry() -> None:
    rec = MapRecord("submap", "test", 4, smoothing=Smoothing(25.0, 0.5))
    assert MapRecord.from_json(rec.to_json()) == rec
    assert rec.to_json()["smoothing"] == {"radius_m": 25.0, "weight": 0.5}
    assert "smoothing" not in MapRecord().to_json()
    across = MapRecord(smoothing=Smoothing(30.0, 1.0, across_drives=True))
    assert across.to_json()["smoothing"]["across_drives"] is True
    assert MapRecord.from_json(across.to_json()) == across
    with pytest.raises(InputError, match="across_drives must be true or false"):
        MapRecord.from_json({"kind": "submap", "smoothing": {"radius_m": 3, "weight": 1,
                                                             "across_drives": "yes"}})  # fmt: skip
    # a weight or across_drives without a radius is refused, not ignored (the default too)
    for weight, across, option in ((None, True, "--smooth-across-drives"),
                                   (0.5, False, "--smooth-weight")):  # fmt: skip
        with pytest.raises(InputError) as err:
            Smoothing.of(None, weight, across_drives=across)
        assert err.value.source == option
    assert Smoothing.of(None) is None
    assert Smoothing.of(30.0) == Smoothing(30.0, 0.5)
    for bad in (
        {"radius_m": "25", "weight": 0.5},
        {"radius_m": 25.0},
        {"radius_m": -1, "weight": 1},
    ):
        with pytest.raises(InputError, match="smoothing") as err:
            MapRecord.from_json({**rec.to_json(), "smoothing": bad}, source="m.json")
        assert err.value.source == "m.json"


# -- bundles -------------------------------------------------------------------------------


def test_a_smoothed_bundle_holds_the_smoothed_descriptors(world, tmp_path: Path) -> None:
    sm = Smoothing(25.0, 0.5)
    rep = ib.build_bundle(
        tmp_path / "s", world["ckpt"], world["tree"], smoothing=sm, progress=False
    )
    assert rep.manifest is not None and rep.manifest.map_record.smoothing == sm
    # a reader that predates smoothing must refuse the bundle, not read it as a plain map
    assert json.loads((rep.path / MANIFEST_FILE).read_text())["version"] == 2
    assert json.loads((world["bundle"] / MANIFEST_FILE).read_text())["version"] == 1
    plain = IndexBundle.load(world["bundle"])
    raw = plain.index.reconstruct_n(0, plain.count)
    md = plain.metadata
    expected = _direct(raw, raw.shape[1], md.run, np.c_[md.northing, md.easting], 25.0, 0.5)
    got = IndexBundle.load(tmp_path / "s").index.reconstruct_n(0, plain.count)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert np.abs(got - raw).max() > 1e-4  # it blended (the random model varies little)


def test_a_map_of_four_headings_blends_heading_by_heading(world, tmp_path: Path) -> None:
    """A model that turns clouds to their own heading: each entry's four vectors (index rows
    4i..4i+3) blend each with the same heading of the neighbours."""
    from tests.index.helpers import make_checkpoint

    ckpt = make_checkpoint(tmp_path / "heading", canonical_heading=True)
    plain = IndexBundle.load(
        ib.build_bundle(tmp_path / "p", ckpt, world["tree"], runs=[RUNS[0]], progress=False).path
    )
    sm = Smoothing(25.0, 0.5)
    rep = ib.build_bundle(
        tmp_path / "s", ckpt, world["tree"], runs=[RUNS[0]], smoothing=sm, progress=False
    )
    smoothed = IndexBundle.load(rep.path)
    assert smoothed.turns == 4 and smoothed.index.ntotal == 4 * PER_RUN
    raw = plain.index.reconstruct_n(0, 4 * PER_RUN)
    dim = raw.shape[1]
    md = plain.metadata
    expected = _direct(
        raw.reshape(PER_RUN, 4 * dim), dim, md.run, np.c_[md.northing, md.easting], 25.0, 0.5
    )
    got = smoothed.index.reconstruct_n(0, 4 * PER_RUN).reshape(PER_RUN, 4 * dim)
    np.testing.assert_allclose(got, expected, atol=1e-5)


def test_adding_to_a_smoothed_bundle_takes_whole_new_runs(world, tmp_path: Path) -> None:
    sm = Smoothing(25.0, 0.5)
    out = tmp_path / "grow"
    ib.build_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[0]], smoothing=sm, progress=False)
    ib.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)
    ib.build_bundle(tmp_path / "both", world["ckpt"], world["tree"], smoothing=sm, progress=False)
    grown, both = IndexBundle.load(out), IndexBundle.load(tmp_path / "both")
    assert grown.manifest.map_record.smoothing == sm and grown.manifest.version == 2
    np.testing.assert_allclose(
        grown.index.reconstruct_n(0, 2 * PER_RUN),
        both.index.reconstruct_n(0, 2 * PER_RUN),
        atol=1e-6,
    )
    # a tree whose run 0 has grown: its new submaps would blend with entries already indexed
    tree = tmp_path / "tree"
    shutil.copytree(world["tree"], tree)
    folder = tree / "oxford" / RUNS[0] / "pointcloud_20m"
    csv = folder.parent / "pointcloud_locations_20m.csv"
    ts = 1_500_000_000_000_000
    shutil.copy(next(folder.glob("*.bin")), folder / f"{ts}.bin")
    csv.write_text(f"timestamp,northing,easting\n{ts},5735400.0,620000.0\n")
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    with pytest.raises(
        InputError, match=f"smoothed along its drives and already holds oxford/{RUNS[0]}"
    ):
        ib.add_to_bundle(out, world["ckpt"], tree, runs=[RUNS[0]], progress=False)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_a_map_smoothed_across_drives_blends_them_and_takes_no_more(world, tmp_path) -> None:
    sm = Smoothing(25.0, 0.5, across_drives=True)
    out = tmp_path / "across"
    ib.build_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[0]], smoothing=sm, progress=False)
    ib.build_bundle(tmp_path / "both", world["ckpt"], world["tree"], smoothing=sm, progress=False)
    plain = IndexBundle.load(world["bundle"])
    raw = plain.index.reconstruct_n(0, plain.count)
    md = plain.metadata
    one_drive = np.zeros(plain.count)
    expected = _direct(raw, raw.shape[1], one_drive, np.c_[md.northing, md.easting], 25.0, 0.5)
    got = IndexBundle.load(tmp_path / "both").index.reconstruct_n(0, plain.count)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    with pytest.raises(InputError, match="smoothed across its drives: build it again"):
        ib.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_commands_take_and_check_the_setting(world, tmp_path: Path) -> None:
    def pnvlad(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "pnvlad_cli.main", *args],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip

    out = tmp_path / "cli.index"
    bad = pnvlad("index", "build", "-m", str(world["ckpt"]), "-r", str(world["tree"]),
                 "-o", str(out), "--smooth", "-5", "--no-progress")  # fmt: skip
    assert bad.returncode == 2 and "smooth" in bad.stderr and not out.exists()
    ok = pnvlad("index", "build", "-m", str(world["ckpt"]), "-r", str(world["tree"]), "-o",
                str(out), "--smooth", "30", "--smooth-weight", "0.4", "--no-progress")  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    info = pnvlad("index", "info", str(out))
    assert "smoothed along its drives (30 m, weight 0.4)" in info.stdout
    doc = json.loads((out / "manifest.json").read_text())
    assert doc["map"]["smoothing"] == {"radius_m": 30.0, "weight": 0.4}
    lone = pnvlad("index", "build", "-m", str(world["ckpt"]), "-r", str(world["tree"]), "-o",
                  str(tmp_path / "lone"), "--smooth-across-drives", "--no-progress")  # fmt: skip
    assert lone.returncode == 2 and "--smooth R" in lone.stderr
    assert not (tmp_path / "lone").exists()
    across = pnvlad("index", "build", "-m", str(world["ckpt"]), "-r", str(world["tree"]), "-o",
                    str(tmp_path / "across"), "--smooth", "25", "--smooth-across-drives",
                    "--no-progress")  # fmt: skip
    assert across.returncode == 0, across.stderr
    info = pnvlad("index", "info", str(tmp_path / "across"))
    assert "smoothed across its drives (25 m, weight 0.5)" in info.stdout
