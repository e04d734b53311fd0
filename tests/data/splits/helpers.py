"""Trees and splits built for the splits tests (hand-placed submaps at exact distances)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from pnvlad_service.data import splits as sp
from pnvlad_service.data.tree import LAYOUTS

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


def train_tree(root: Path) -> Path:
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


def eval_tree(root: Path) -> Path:
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


def full_splits(root: Path) -> sp.Splits:
    train_tree(root)
    eval_tree(root)
    return sp.build_splits(root, regions=REG)


def assert_tuples_equal(a: sp.TrainingTuples, b: sp.TrainingTuples, coords: bool = True) -> None:
    assert a.files == b.files
    assert [x.tolist() for x in a.positives] == [x.tolist() for x in b.positives]
    assert [x.tolist() for x in a.near] == [x.tolist() for x in b.near]
    if coords:
        assert a.northing.tolist() == b.northing.tolist()
        assert a.easting.tolist() == b.easting.tolist()


def assert_eval_equal(a: sp.EvaluationSet, b: sp.EvaluationSet) -> None:
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


class PlainOnly(pickle.Unpickler):
    """The test's own class-refusing unpickler, independent of io.pickles."""

    def find_class(self, module, name):
        raise AssertionError(f"pickle names {module}.{name}")
