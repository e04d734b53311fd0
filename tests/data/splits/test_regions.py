"""data.splits.regions: strict membership at 150 m, the built-in regions, regions files.

Expected values come from hand-worked cases (points placed at exactly 10, 25, 50 and 150 m
along one axis, where float64 arithmetic on UTM magnitudes is exact) and from plain Python
loops over every pair of submaps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data import splits as sp
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import InputError
from tests.data.splits.helpers import (
    CE,
    CN,
    REG,
    make_run,
)


def test_region_membership_is_strict_at_150_m() -> None:
    n = np.array([CN + 150.0, CN - 150.0, CN + 149.75, CN - 149.75, CN, CN, CN, CN + 149.75])
    e = np.array([CE, CE, CE, CE, CE + 150.0, CE - 150.0, CE - 149.75, CE + 150.0])
    assert REG.contains(n, e).tolist() == [False, False, True, True, False, False, True, False]
    assert sp.TestRegions(everything=True).contains(n, e).all()
    assert not sp.TestRegions().contains(n, e).any()


@settings(max_examples=50, deadline=None)
@given(
    pts=st.lists(
        st.tuples(st.integers(-800, 800), st.integers(-800, 800)), min_size=1, max_size=30
    ),
    half=st.integers(1, 700),
)
def test_region_membership_matches_a_plain_loop(pts, half) -> None:
    centres = ((CN, CE), (CN + 300.0, CE - 200.0))
    reg = sp.TestRegions(centres, half * 0.5)
    n = np.array([CN + a * 0.5 for a, _ in pts])
    e = np.array([CE + b * 0.5 for _, b in pts])
    expect = [
        any(abs(ni - c0) < half * 0.5 and abs(ei - c1) < half * 0.5 for c0, c1 in centres)
        for ni, ei in zip(n, e, strict=True)
    ]
    assert reg.contains(n, e).tolist() == expect


def test_oxford_regions_are_built_in() -> None:
    ox = sp.TestRegions.oxford()
    assert len(ox.centres) == 4 and ox.half_size == 150.0
    assert ox.contains(np.array([5735712.768124]), np.array([620084.402381 + 149.9]))[0]


def test_regions_files_json_and_csv(tmp_path: Path) -> None:
    one = sp.TestRegions(((1.0, 2.0), (3.5, 4.25)), 120.0)
    sp.save_regions(tmp_path / "r.json", one)
    assert sp.load_regions(tmp_path / "r.json") == one
    many = {"business": sp.TestRegions(everything=True), "residential": one}
    sp.save_regions(tmp_path / "m.json", many)
    assert sp.load_regions(tmp_path / "m.json") == many
    (tmp_path / "r.csv").write_text("northing,easting,half_size\n1,2,120\n3.5,4.25,120\n")
    assert sp.load_regions(tmp_path / "r.csv") == one
    (tmp_path / "d.csv").write_text("dataset,northing,easting\na,1,2\nb,3,4\n")
    assert sp.load_regions(tmp_path / "d.csv") == {
        "a": sp.TestRegions(((1.0, 2.0),)),
        "b": sp.TestRegions(((3.0, 4.0),)),
    }
    (tmp_path / "bad.json").write_text('{"centres": [[1, "x"]]}')
    with pytest.raises(InputError, match="bad test regions"):
        sp.load_regions(tmp_path / "bad.json")
    (tmp_path / "neg.json").write_text('{"centres": [], "half_size": -1}')
    with pytest.raises(InputError, match="half_size"):
        sp.load_regions(tmp_path / "neg.json")


def test_unknown_dataset_needs_regions_and_tree_file_is_used(tmp_path: Path) -> None:
    make_run(tmp_path, "city", "run1", {"test": [(1, 10.0, 10.0)]})
    make_run(tmp_path, "city", "run2", {"test": [(2, 12.0, 10.0)]})
    tree = BenchmarkTree(tmp_path)
    with pytest.raises(InputError, match="no test regions known for 'city'"):
        sp.build_evaluation_sets(tree, "city")
    sp.save_regions(tmp_path / "city" / sp.REGIONS_FILE, sp.TestRegions(((0.0, 0.0),), 11.0))
    (es,) = sp.build_evaluation_sets(tree, "city")
    assert [len(q) for q in es.queries] == [1, 0]  # 10 < 11 inside, 12 outside
