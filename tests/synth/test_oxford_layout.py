"""A synthetic tree in the published Oxford layout: one area named oxford, laid over the
benchmark's own test regions, its submaps cut to a box; ``pnvlad data splits --dataset oxford``
gives the paper's evaluation structure, checked against sets computed here from the CSVs."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.splits import load_splits
from pnvlad_service.errors import InputError
from pnvlad_service.synth.generate import AreaSpec, generate, get_preset

#: The four Oxford test squares (northing, easting), +-150 m, as the benchmark publishes them.
OXFORD = [
    (5735712.768124, 620084.402381),
    (5735611.299219, 620540.270327),
    (5735237.358209, 620543.094379),
    (5734749.303802, 619932.693364),
]
HALF = 150.0
#: The tiny district placed so that the first square covers the east half of its route.
ORIGIN = (620084.402381 - HALF - 130.0, 5735712.768124 - HALF - 50.0)


def _preset(**area: object) -> object:
    spec = get_preset("tiny")
    oxford = AreaSpec(
        name="oxford",
        district="business",
        size=(360.0, 300.0),
        origin=ORIGIN,
        route_m=260.0,
        test_regions="published",
    ).model_copy(update=area)
    return spec.model_copy(
        update={
            "name": "tiny_oxford",
            "areas": [oxford],
            "box_m": 30.0,
            "keyframe_stride": None,
            "raw_scans": False,
        }
    )


@pytest.fixture(scope="module")
def oxford_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("oxford") / "tree"
    generate(_preset(), root, seed=3, workers=2, progress=False)
    return root


def _rows(path: Path) -> list[tuple[str, float, float]]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["timestamp", "northing", "easting"]
    return [(t, float(n), float(e)) for t, n, e in rows[1:]]


def _inside(n: float, e: float) -> bool:
    return any(cn - HALF < n < cn + HALF and ce - HALF < e < ce + HALF for cn, ce in OXFORD)


def test_the_tree_is_the_published_oxford_layout(oxford_tree: Path) -> None:
    assert sorted(p.name for p in oxford_tree.iterdir()) == [
        "oxford",
        "splits.json",
        "synth.json",
    ]
    runs = sorted(p.name for p in (oxford_tree / "oxford").iterdir() if p.is_dir())
    assert len(runs) == 3 and all(re.fullmatch(r"\d{4}(-\d\d){5}", r) for r in runs)
    for run in runs:
        d = oxford_tree / "oxford" / run
        for folder, name in (
            ("pointcloud_20m", "pointcloud_locations_20m.csv"),
            ("pointcloud_20m_10overlap", "pointcloud_locations_20m_10overlap.csv"),
        ):
            rows = _rows(d / name)
            assert sorted(f"{t}.bin" for t, _, _ in rows) == sorted(
                p.name for p in (d / folder).iterdir()
            )
            assert all((d / folder / f"{t}.bin").stat().st_size == 98_304 for t, _, _ in rows)
            # The submaps were cut to the preset's 30 m box, and their record says so.
            record = json.loads((d / f".prepare-{folder}.json").read_text())
            assert record["box_m"] == 30.0
    regions = json.loads((oxford_tree / "oxford" / "test_regions.json").read_text())
    assert regions["centres"] == [list(c) for c in OXFORD] and regions["half_size"] == HALF


def test_data_splits_gives_each_run_against_every_other(oxford_tree: Path, tmp_path: Path) -> None:
    out = tmp_path / "splits.json"
    res = CliRunner().invoke(
        app, ["data", "splits", str(oxford_tree), "--dataset", "oxford", "-o", str(out)]
    )
    assert res.exit_code == 0, res.output
    splits = load_splits(out)
    assert list(splits.evaluation) == ["oxford"] and list(splits.training) == ["oxford"]
    es = splits.evaluation["oxford"]
    runs = sorted(p.name for p in (oxford_tree / "oxford").iterdir() if p.is_dir())
    assert es.runs == runs
    db = [_rows(oxford_tree / "oxford" / r / "pointcloud_locations_20m.csv") for r in runs]
    for j, run in enumerate(runs):
        # The database: every test-layout submap of the run; the queries: those inside.
        assert es.database[j].files == [f"oxford/{run}/pointcloud_20m/{t}.bin" for t, _, _ in db[j]]
        queries = [(t, n, e) for t, n, e in db[j] if _inside(n, e)]
        assert 0 < len(queries) < len(db[j])
        assert es.queries[j].files == [
            f"oxford/{run}/pointcloud_20m/{t}.bin" for t, _, _ in queries
        ]
        assert sorted(es.truth[j]) == [i for i in range(len(runs)) if i != j]
        for i in es.truth[j]:
            for q, (_, n, e) in enumerate(queries):
                near = [
                    k for k, (_, n2, e2) in enumerate(db[i]) if (n2 - n) ** 2 + (e2 - e) ** 2 <= 625
                ]
                assert es.truth[j][i][q].tolist() == near
            assert any(len(t) for t in es.truth[j][i])  # every ordered pair is scored
    # Training: the training-layout submaps outside the squares, every run pooled.
    train = [
        (f"oxford/{r}/pointcloud_20m_10overlap/{t}.bin", n, e)
        for r in runs
        for t, n, e in _rows(oxford_tree / "oxford" / r / "pointcloud_locations_20m_10overlap.csv")
        if not _inside(n, e)
    ]
    tuples = splits.training["oxford"]
    assert tuples.files == [f for f, _, _ in train]
    ne = np.array([(n, e) for _, n, e in train])
    d2 = ((ne[:, None] - ne[None]) ** 2).sum(-1)
    for k in range(len(train)):
        assert tuples.positives[k].tolist() == [m for m in np.flatnonzero(d2[k] <= 100) if m != k]
        assert tuples.negatives(k).tolist() == np.flatnonzero(d2[k] > 2500).tolist()
    assert len(tuples.anchors(2)) > 0


def test_published_regions_the_route_misses_are_refused(tmp_path: Path) -> None:
    far = _preset(origin=(600000.0, 5700000.0))
    with pytest.raises(InputError) as exc:
        generate(far, tmp_path / "far", seed=3, workers=1, progress=False)
    assert exc.value.source == "test_regions" and "crosses none" in str(exc.value)
    other = _preset(name="business")
    with pytest.raises(InputError, match="oxford only"):
        generate(other, tmp_path / "other", seed=3, workers=1, progress=False)
    assert not (tmp_path / "far").exists() and not (tmp_path / "other").exists()


@pytest.mark.parametrize("bad", [0.0, -25.0, float("nan"), float("inf")])
def test_a_bad_preset_box_is_refused_naming_box_m(tmp_path: Path, bad: float) -> None:
    spec = get_preset("tiny")
    with pytest.raises(ValueError, match="box_m"):
        type(spec).model_validate({**spec.model_dump(), "box_m": bad})
    with pytest.raises(InputError) as exc:  # a copy skips the model's check; generate does not
        generate(spec.model_copy(update={"box_m": bad}), tmp_path / "t", progress=False)
    assert exc.value.source == "box_m" and "\n" not in str(exc.value)
    assert not (tmp_path / "t").exists()
