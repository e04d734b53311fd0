"""splits.py: the published rules at their exact boundaries, our format, the published pickles.

Expected values come from hand-worked cases (points placed at exactly 10, 25, 50 and 150 m
along one axis, where float64 arithmetic on UTM magnitudes is exact) and from plain Python
loops over every pair of submaps.
"""

from __future__ import annotations

import io
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from pnvlad_service.data import splits as sp
from pnvlad_service.data.tree import LAYOUTS, BenchmarkTree
from pnvlad_service.errors import InputError
from pnvlad_service.io.pickles import dump_plain, safe_load

# A centre whose coordinates are exact binary fractions, so c ± 150 is exact too.
CN, CE = 5735712.75, 620084.25
REG = sp.TestRegions(((CN, CE),), 150.0)


def make_run(root: Path, dataset: str, run: str, rows: dict, layout: str = "oxford") -> None:
    lay = LAYOUTS[layout]
    for kind, kind_rows in rows.items():
        folder = root / dataset / run / lay.folder(kind)
        folder.mkdir(parents=True, exist_ok=True)
        lines = ["timestamp,northing,easting"]
        for t, n, e in kind_rows:
            np.zeros((4096, 3)).tofile(folder / f"{t}.bin")
            lines.append(f"{t},{float(n)!r},{float(e)!r}")
        (root / dataset / run / lay.csv(kind)).write_text("\n".join(lines) + "\n")


def brute_within(ref: list[tuple[float, float]], q: tuple[float, float], r: float) -> list[int]:
    out = []
    for k, (n, e) in enumerate(ref):
        dn, de = n - q[0], e - q[1]
        if dn * dn + de * de <= r * r:
            out.append(k)
    return out


# ------------------------------------------------------------------ regions


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


# ------------------------------------------------------------------ distances


def test_within_radius_is_inclusive_at_exact_distances() -> None:
    # one reference point, queries exactly 10, 25, 50 m away along each axis and on a 6-8-10
    # diagonal; and a hair beyond
    ref_n, ref_e = np.array([CN]), np.array([CE])
    offsets = [(10.0, 0.0), (0.0, -25.0), (-50.0, 0.0), (6.0, 8.0), (0.0, 10.000001)]
    qn = np.array([CN + a for a, _ in offsets])
    qe = np.array([CE + b for _, b in offsets])
    hits = lambda r: [len(x) == 1 for x in sp.within_radius(ref_n, ref_e, qn, qe, r)]  # noqa: E731
    assert hits(10.0) == [True, False, False, True, False]
    assert hits(25.0) == [True, True, False, True, True]
    assert hits(50.0) == [True, True, True, True, True]
    assert hits(9.999999) == [False, False, False, False, False]


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.tuples(st.integers(-120, 120), st.integers(-120, 120)), min_size=1, max_size=40),
    st.sampled_from([0.0, 5.0, 10.0, 25.0, 50.0]),
)
def test_within_radius_matches_a_plain_loop(pts, r) -> None:
    ref = [(CN + a * 0.5, CE + b * 0.5) for a, b in pts]
    n = np.array([p[0] for p in ref])
    e = np.array([p[1] for p in ref])
    expect = [brute_within(ref, q, r) for q in ref]
    assert [g.tolist() for g in sp.within_radius(n, e, n, e, r)] == expect
    assert [g.tolist() for g in sp.within_radius(n, e, n, e, r, chunk=7)] == expect


# ------------------------------------------------------------------ training tuples


def _train_tree(root: Path) -> Path:
    # run A: anchor at offset 0; others at exactly 10 (positive), 10.25 (neither), 50 (not a
    # negative), 50.25 (negative), and one inside the test region. CSV rows not in time order.
    base = CN - 1000.0
    make_run(
        root,
        "oxford",
        "2014-a",
        {
            "train": [
                (50, base, CE),
                (40, base + 10.0, CE),
                (30, base, CE - 10.25),
                (20, base + 50.0, CE),
                (10, base, CE + 50.25),
                (60, CN + 10.0, CE),  # inside the test region
            ]
        },
    )
    # run B: the same place as A's anchor (a positive across runs) and a far submap
    make_run(
        root,
        "oxford",
        "2014-b",
        {"train": [(70, base, CE), (80, base - 400.0, CE), (90, CN - 149.75, CE + 149.75)]},
    )
    return root


def test_training_tuples_boundaries_and_order(tmp_path: Path) -> None:
    tree = BenchmarkTree(_train_tree(tmp_path))
    t = sp.build_training_tuples(tree, "oxford", REG)
    # runs sorted, CSV row order, region submaps dropped
    assert [f.rsplit("/", 1)[1] for f in t.files] == [
        "50.bin",
        "40.bin",
        "30.bin",
        "20.bin",
        "10.bin",
        "70.bin",
        "80.bin",
    ]
    assert t.files[0] == "oxford/2014-a/pointcloud_20m_10overlap/50.bin"
    assert t.positives[0].tolist() == [1, 5]  # 10 m exactly, and run B at 0 m; not itself
    assert t.negatives(0).tolist() == [4, 6]  # 50.25 m and 400 m; 50 m exactly is not
    assert 3 not in t.negatives(0) and 2 not in t.negatives(0) and 2 not in t.positives[0]
    assert t.positives[1].tolist() == [0, 5]  # both exactly 10 m away
    assert t.positives[2].tolist() == []  # 10.25 m from 0 and 5
    assert t.anchors(2).tolist() == [0, 1, 5]
    assert t.anchors(3).tolist() == []
    inside = sp.build_training_tuples(tree, "oxford", REG, inside=True)
    assert [f.rsplit("/", 1)[1] for f in inside.files] == ["60.bin", "90.bin"]


def test_training_tuples_match_a_plain_loop(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rows = {}
    for r in range(3):
        pts = rng.integers(-240, 240, size=(40, 2)) * 0.5
        rows[r] = [(1000 * r + k, CN - 600 + a, CE + b) for k, (a, b) in enumerate(pts)]
        make_run(tmp_path, "oxford", f"run{r}", {"train": rows[r]})
    t = sp.build_training_tuples(BenchmarkTree(tmp_path), "oxford", REG)
    pooled = [(n, e) for r in range(3) for _, n, e in rows[r] if not (abs(n - CN) < 150)]
    assert len(t) == len(pooled)
    for i, q in enumerate(pooled):
        assert t.positives[i].tolist() == [k for k in brute_within(pooled, q, 10.0) if k != i]
        near = brute_within(pooled, q, 50.0)
        assert t.negatives(i).tolist() == [k for k in range(len(pooled)) if k not in near]


# ------------------------------------------------------------------ evaluation sets


def _eval_tree(root: Path) -> Path:
    # three runs along the easting axis through the region centre; positions are exact
    offs = {
        "r1": [-300.0, -100.0, 0.0, 40.0, 149.75],
        "r2": [-75.0, 25.0, 65.0, 250.0],
        "r3": [-100.0, -24.75, 0.0, 25.25, 150.0],
    }
    for k, (run, o) in enumerate(offs.items()):
        make_run(
            root, "oxford", run, {"test": [(k * 100 + i, CN, CE + x) for i, x in enumerate(o)]}
        )
    return root


def test_evaluation_sets_by_hand(tmp_path: Path) -> None:
    (es,) = sp.build_evaluation_sets(BenchmarkTree(_eval_tree(tmp_path)), "oxford", REG)
    assert es.name == "oxford" and es.runs == ["r1", "r2", "r3"]
    assert [len(d) for d in es.database] == [5, 4, 5]
    # queries: inside ±150 strictly; 149.75 in, 150 out, 250 and -300 out
    assert [len(q) for q in es.queries] == [4, 3, 4]
    assert es.query_db_index(0).tolist() == [1, 2, 3, 4]
    assert es.query_db_index(2).tolist() == [0, 1, 2, 3]
    # query r1@0: r2 database within 25 m inclusive -> offset 25 (exactly 25 m); r3 -> -24.75, 0
    q0 = 1  # r1's queries are offsets -100, 0, 40, 149.75
    assert es.truth[0][1][q0].tolist() == [1]
    assert es.truth[0][2][q0].tolist() == [1, 2]
    # query r2@25 in r3: 25.25 is 0.25 away, 0 is exactly 25 m away (inclusive)
    assert es.truth[1][2][1].tolist() == [2, 3]
    # query r1@149.75 has nothing within 25 m in r2 (nearest 65)
    assert es.truth[0][1][3].tolist() == []
    assert set(es.truth[0]) == {1, 2} and set(es.truth[1]) == {0, 2}


def test_evaluation_truth_matches_a_plain_loop(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    runs = {}
    for r in range(4):
        pts = rng.integers(-400, 400, size=(30, 2)) * 0.5
        runs[f"run{r}"] = [(r * 100 + k, CN + a, CE + b) for k, (a, b) in enumerate(pts)]
        make_run(tmp_path, "oxford", f"run{r}", {"test": runs[f"run{r}"]})
    (es,) = sp.build_evaluation_sets(BenchmarkTree(tmp_path), "oxford", REG)
    names = sorted(runs)
    for j, qrun in enumerate(names):
        qs = [(n, e) for _, n, e in runs[qrun] if abs(n - CN) < 150 and abs(e - CE) < 150]
        assert len(es.queries[j]) == len(qs)
        for i, drun in enumerate(names):
            if i == j:
                continue
            db = [(n, e) for _, n, e in runs[drun]]
            assert [x.tolist() for x in es.truth[j][i]] == [brute_within(db, q, 25.0) for q in qs]


def test_inhouse_runs_group_by_area_with_builtin_regions(tmp_path: Path) -> None:
    for k in (1, 2):
        make_run(
            tmp_path,
            "inhouse_datasets",
            f"business_run{k}",
            {"test": [(k * 10, 100.0, 200.0 + k)]},
            "inhouse",
        )
        n, e = sp.INHOUSE_CENTRES["residential"][0]
        make_run(
            tmp_path,
            "inhouse_datasets",
            f"residential_run{k}",
            {"test": [(k * 10 + 1, n, e), (k * 10 + 2, n + 500.0, e)]},
            "inhouse",
        )
    sets = sp.build_evaluation_sets(BenchmarkTree(tmp_path), "inhouse_datasets")
    by = {s.name: s for s in sets}
    assert set(by) == {"business", "residential"}
    assert [len(q) for q in by["business"].queries] == [1, 1]  # everything is a query
    assert [len(q) for q in by["residential"].queries] == [1, 1]


def test_unknown_dataset_needs_regions_and_tree_file_is_used(tmp_path: Path) -> None:
    make_run(tmp_path, "city", "run1", {"test": [(1, 10.0, 10.0)]})
    make_run(tmp_path, "city", "run2", {"test": [(2, 12.0, 10.0)]})
    tree = BenchmarkTree(tmp_path)
    with pytest.raises(InputError, match="no test regions known for 'city'"):
        sp.build_evaluation_sets(tree, "city")
    sp.save_regions(tmp_path / "city" / sp.REGIONS_FILE, sp.TestRegions(((0.0, 0.0),), 11.0))
    (es,) = sp.build_evaluation_sets(tree, "city")
    assert [len(q) for q in es.queries] == [1, 0]  # 10 < 11 inside, 12 outside


def test_published_run_selection(tmp_path: Path) -> None:
    runs = [f"2014-{k:02d}" for k in range(45)]
    for k, run in enumerate(runs):
        make_run(
            tmp_path,
            "oxford",
            run,
            {"train": [(k * 10, CN - 500.0, CE)], "test": [(k * 10 + 1, CN, CE)]},
        )
    s = sp.build_splits(tmp_path, published=True)
    picked = [5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 22, 24, 31, 32, 33, 38, 39, 43]
    assert s.evaluation["oxford"].runs == [runs[k] for k in [*picked, 44]]
    assert [f.split("/")[1] for f in s.training["oxford"].files] == runs[:44]  # not the last
    everything = sp.build_splits(tmp_path)
    assert len(everything.evaluation["oxford"].runs) == 45
    assert len(everything.training["oxford"]) == 45
    # the published indices count files too: a file in the folder shifts them
    shutil.rmtree(tmp_path / "oxford" / "2014-44")
    (tmp_path / "oxford" / "2014-44").write_text("not a run")
    with pytest.raises(InputError, match=r"\['2014-44'\] .* not run folders"):
        sp.build_splits(tmp_path, published=True)


# ------------------------------------------------------------------ our format


def _full_splits(root: Path) -> sp.Splits:
    _train_tree(root)
    _eval_tree(root)
    return sp.build_splits(root, regions=REG)


def _assert_tuples_equal(a: sp.TrainingTuples, b: sp.TrainingTuples, coords: bool = True) -> None:
    assert a.files == b.files
    assert [x.tolist() for x in a.positives] == [x.tolist() for x in b.positives]
    assert [x.tolist() for x in a.near] == [x.tolist() for x in b.near]
    if coords:
        assert a.northing.tolist() == b.northing.tolist()
        assert a.easting.tolist() == b.easting.tolist()


def _assert_eval_equal(a: sp.EvaluationSet, b: sp.EvaluationSet) -> None:
    assert a.runs == b.runs
    for x, y in zip(a.database + a.queries, b.database + b.queries, strict=True):
        assert (x.files, x.northing.tolist(), x.easting.tolist()) == (
            y.files,
            y.northing.tolist(),
            y.easting.tolist(),
        )
    for ta, tb in zip(a.truth, b.truth, strict=True):
        assert set(ta) == set(tb)
        assert {i: [v.tolist() for v in ta[i]] for i in ta} == {
            i: [v.tolist() for v in tb[i]] for i in tb
        }


@pytest.mark.parametrize("pack", [False, True])
def test_save_load_round_trip(tmp_path: Path, pack: bool) -> None:
    s = _full_splits(tmp_path / "tree")
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
    _assert_tuples_equal(s.training["oxford"], back.training["oxford"])
    _assert_tuples_equal(s.test_tuples["oxford"], back.test_tuples["oxford"])
    _assert_eval_equal(s.evaluation["oxford"], back.evaluation["oxford"])
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
    sp.save_splits(tmp_path / "s.json", _full_splits(tmp_path / "tree"))
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
    back = sp._Reader(Path("x.json")).index_lists(packed, len(arrays), 2**31 - 1, "f")
    assert [b.tolist() for b in back] == [sorted(x) for x in lists]


def test_packed_lists_malformed(tmp_path: Path) -> None:
    r = sp._Reader(tmp_path / "s.json")
    good = sp.pack_lists([np.array([1, 4]), np.array([2])])
    with pytest.raises(InputError, match="lengths do not describe 3 lists"):
        r.index_lists(good, 3, 10, "f")
    with pytest.raises(InputError, match=r"out of range 0\.\.3"):
        r.index_lists(good, 2, 4, "f")
    with pytest.raises(InputError, match="cannot decode"):
        r.index_lists({**good, "deltas": "@@@"}, 2, 10, "f")
    with pytest.raises(InputError, match="unknown packing"):
        r.index_lists({**good, "packing": "lz4"}, 2, 10, "f")


# ------------------------------------------------------------------ published pickles


class PlainOnly(pickle.Unpickler):
    """The test's own class-refusing unpickler, independent of safe_pickle."""

    def find_class(self, module, name):
        raise AssertionError(f"pickle names {module}.{name}")


def test_export_matches_the_published_structures(tmp_path: Path) -> None:
    s = _full_splits(tmp_path / "tree")
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
    s = _full_splits(tmp_path / "tree")
    sp.export_pickles(s, tmp_path / "pk")
    back = sp.import_pickles([tmp_path / "pk"])
    _assert_tuples_equal(s.training["oxford"], back.training["oxford"], coords=False)
    _assert_tuples_equal(s.test_tuples["oxford"], back.test_tuples["oxford"], coords=False)
    _assert_eval_equal(s.evaluation["oxford"], back.evaluation["oxford"])
    assert back.evaluation["oxford"].runs == ["r1", "r2", "r3"]
    # and the imported splits survive our own format (null coordinates)
    sp.save_splits(tmp_path / "imp.json", back)
    again = sp.load_splits(tmp_path / "imp.json")
    assert again.training["oxford"].northing is None
    _assert_eval_equal(back.evaluation["oxford"], again.evaluation["oxford"])


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


# ------------------------------------------------------------------ CLI


def test_cli_splits_export_import(tmp_path: Path) -> None:
    from pnvlad_cli.main import app

    root = tmp_path / "tree"
    _train_tree(root)
    _eval_tree(root)
    sp.save_regions(tmp_path / "regions.json", REG)
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "data",
            "splits",
            str(root),
            "--regions",
            str(tmp_path / "regions.json"),
            "--out",
            str(tmp_path / "s.json"),
            "--export-pickles",
            str(tmp_path / "pk"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "oxford: 7 training tuples (3 with >= 2 positives), 2 test tuples" in res.output
    assert "oxford: 3 runs, 14 database submaps, 11 queries" in res.output
    res = runner.invoke(
        app, ["data", "import-pickles", str(tmp_path / "pk"), "-o", str(tmp_path / "i.json")]
    )
    assert res.exit_code == 0, res.output
    _assert_eval_equal(
        sp.load_splits(tmp_path / "s.json").evaluation["oxford"],
        sp.load_splits(tmp_path / "i.json").evaluation["oxford"],
    )
    # a dataset without known regions: a clean error, exit 2
    make_run(root, "city", "run1", {"test": [(1, 0.0, 0.0)]})
    res = runner.invoke(
        app, ["data", "splits", str(root), "-d", "city", "-o", str(tmp_path / "c.json")]
    )
    assert res.exit_code == 2 and "no test regions known" in res.output
    assert not (tmp_path / "c.json").exists()
