"""data.splits.codec: our JSON format round trips, packed lists, malformed files refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data import splits as sp
from pnvlad_service.data.splits import codec
from pnvlad_service.errors import InputError
from tests.data.splits.helpers import (
    assert_eval_equal,
    assert_tuples_equal,
    full_splits,
)


@pytest.mark.parametrize("pack", [False, True])
def test_save_load_round_trip(tmp_path: Path, pack: bool) -> None:
    s = full_splits(tmp_path / "tree")
    assert set(s.training) == {"oxford"} and set(s.evaluation) == {"oxford"}
    sp.save_splits(tmp_path / "s.json", s, pack=pack)
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["format"] == "pnvlad-splits" and doc["version"] == 1
    positives = doc["training"]["oxford"]["positives"]
    if pack:
        assert positives["packing"] == "delta-zlib-base64"
    else:
        assert positives[0] == [1, 5]
    back = sp.load_splits(tmp_path / "s.json")
    assert_tuples_equal(s.training["oxford"], back.training["oxford"])
    assert_tuples_equal(s.test_tuples["oxford"], back.test_tuples["oxford"])
    assert_eval_equal(s.evaluation["oxford"], back.evaluation["oxford"])
    assert back.params["pos_radius"] == 10.0 and back.params["truth_radius"] == 25.0


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda d: d.update(format="other"), "not a pnvlad-splits"),
        (lambda d: d.update(version=2), "version 2"),
        (lambda d: d["training"]["oxford"]["positives"][0].append(99), r"positives\[0\].*range"),
        (lambda d: d["training"]["oxford"].pop("files"), "missing field 'files'"),
        (
            lambda d: d["evaluation"]["oxford"]["queries"][0]["truth"].pop("1"),
            "missing run 1",
        ),
        (lambda d: d["evaluation"]["oxford"]["queries"][0]["truth"]["2"][0].append(-1), "range"),
    ],
)
def test_load_rejects_malformed_files(tmp_path: Path, mutate, match: str) -> None:
    sp.save_splits(tmp_path / "s.json", full_splits(tmp_path / "tree"))
    doc = json.loads((tmp_path / "s.json").read_text())
    mutate(doc)
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=match) as exc:
        sp.load_splits(tmp_path / "bad.json")
    assert exc.value.source == str(tmp_path / "bad.json")


@settings(max_examples=40, deadline=None)
@given(st.lists(st.lists(st.integers(0, 2**31 - 2), max_size=8), max_size=8))
def test_packed_lists_round_trip(lists) -> None:
    arrays = [np.asarray(sorted(x), dtype=np.int64) for x in lists]
    packed = sp.pack_lists(arrays)
    back = codec._Reader(Path("x.json")).index_lists(packed, len(arrays), 2**31 - 1, "f")
    assert [b.tolist() for b in back] == [sorted(x) for x in lists]


def test_packed_lists_malformed(tmp_path: Path) -> None:
    r = codec._Reader(tmp_path / "s.json")
    good = sp.pack_lists([np.array([1, 4]), np.array([2])])
    with pytest.raises(InputError, match="lengths do not describe 3 lists"):
        r.index_lists(good, 3, 10, "f")
    with pytest.raises(InputError, match=r"out of range 0\.\.3"):
        r.index_lists(good, 2, 4, "f")
    with pytest.raises(InputError, match="cannot decode"):
        r.index_lists({**good, "deltas": "@@@"}, 2, 10, "f")
    with pytest.raises(InputError, match="unknown packing"):
        r.index_lists({**good, "packing": "lz4"}, 2, 10, "f")
