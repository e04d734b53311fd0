"""data.splits.pickles: the published structures written, read back, bad ones refused."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from pnvlad_service.data import splits as sp
from pnvlad_service.errors import InputError
from pnvlad_service.io.pickles import dump_plain, safe_load
from tests.data.splits.helpers import (
    CE,
    CN,
    PlainOnly,
    assert_eval_equal,
    assert_tuples_equal,
    full_splits,
)


def test_export_matches_the_published_structures(tmp_path: Path) -> None:
    s = full_splits(tmp_path / "tree")
    written = sp.export_pickles(s, tmp_path / "pk")
    assert sorted(p.name for p in written) == [
        "oxford_evaluation_database.pickle",
        "oxford_evaluation_query.pickle",
        "test_queries_baseline.pickle",
        "training_queries_baseline.pickle",
    ]
    for p in written:
        plain = PlainOnly(io.BytesIO(p.read_bytes())).load()
        assert plain == safe_load(p)
    tr = safe_load(tmp_path / "pk" / "training_queries_baseline.pickle")
    t = s.training["oxford"]
    assert list(tr) == list(range(len(t)))
    assert tr[0] == {
        "query": "oxford/2014-a/pointcloud_20m_10overlap/50.bin",
        "positives": [1, 5],
        "negatives": [4, 6],
    }
    db = safe_load(tmp_path / "pk" / "oxford_evaluation_database.pickle")
    q = safe_load(tmp_path / "pk" / "oxford_evaluation_query.pickle")
    assert len(db) == 3 and len(q) == 3
    assert db[0][2] == {"query": "oxford/r1/pointcloud_20m/2.bin", "northing": CN, "easting": CE}
    # query r1@0 (key 1): {'query', 'northing', 'easting', 1: [...], 2: [...]}
    assert q[0][1] == {
        "query": "oxford/r1/pointcloud_20m/2.bin",
        "northing": CN,
        "easting": CE,
        1: [1],
        2: [1, 2],
    }
    assert set(q[1][0]) == {"query", "northing", "easting", 0, 2}


def test_import_round_trip(tmp_path: Path) -> None:
    s = full_splits(tmp_path / "tree")
    sp.export_pickles(s, tmp_path / "pk")
    back = sp.import_pickles([tmp_path / "pk"])
    assert_tuples_equal(s.training["oxford"], back.training["oxford"], coords=False)
    assert_tuples_equal(s.test_tuples["oxford"], back.test_tuples["oxford"], coords=False)
    assert_eval_equal(s.evaluation["oxford"], back.evaluation["oxford"])
    assert back.evaluation["oxford"].runs == ["r1", "r2", "r3"]
    # and the imported splits survive our own format (null coordinates)
    sp.save_splits(tmp_path / "imp.json", back)
    again = sp.load_splits(tmp_path / "imp.json")
    assert again.training["oxford"].northing is None
    assert_eval_equal(back.evaluation["oxford"], again.evaluation["oxford"])


def test_import_rejects_bad_structures(tmp_path: Path) -> None:
    good_db = [{0: {"query": "d/r1/f/1.bin", "northing": 1.0, "easting": 2.0}}] * 2
    q = [
        {0: {"query": "d/r1/f/1.bin", "northing": 1.0, "easting": 2.0, 1: [0]}},
        {0: {"query": "d/r2/f/1.bin", "northing": 1.0, "easting": 2.0, 0: [5]}},
    ]
    dump_plain(good_db, tmp_path / "x_evaluation_database.pickle")
    dump_plain(q, tmp_path / "x_evaluation_query.pickle")
    with pytest.raises(InputError, match=r"run 1 query 0 \[0\]: index out of range"):
        sp.import_pickles([tmp_path])
    q[1][0][0] = [0]
    del q[0][0][1]
    dump_plain(q, tmp_path / "x_evaluation_query.pickle")
    with pytest.raises(InputError, match="no ground truth for run 1"):
        sp.import_pickles([tmp_path])
    q[0][0][1] = [0]
    dump_plain(q, tmp_path / "x_evaluation_query.pickle")
    es = sp.import_pickles([tmp_path]).evaluation["x"]
    assert es.runs == ["r1", "r1"] and es.truth[1][0][0].tolist() == [0]
    dump_plain({0: {"query": "a", "positives": [3], "negatives": []}}, tmp_path / "b.pickle")
    (tmp_path / "b.pickle").rename(tmp_path / "training_queries_x.pickle")
    with pytest.raises(InputError, match="entry 0 positives: index out of range"):
        sp.import_pickles([tmp_path / "training_queries_x.pickle"])
    for bad in ([0.0], ["0"], [[0]], 7, [2**70]):
        dump_plain(
            {0: {"query": "a", "positives": [], "negatives": bad}},
            tmp_path / "training_queries_x.pickle",
        )
        with pytest.raises(InputError, match="entry 0 negatives: expected a list of integers"):
            sp.import_pickles([tmp_path / "training_queries_x.pickle"])
    with pytest.raises(InputError, match="no published pickle"):
        sp.import_pickles([tmp_path / "x_evaluation_query.pickle"])
