"""data.splits.build: the runs the published scripts picked, and `pnvlad data splits`."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pnvlad_service.data import splits as sp
from pnvlad_service.errors import InputError
from tests.data.splits.helpers import (
    CE,
    CN,
    REG,
    assert_eval_equal,
    eval_tree,
    make_run,
    train_tree,
)


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


def test_cli_splits_export_import(tmp_path: Path) -> None:
    from pnvlad_cli.main import app

    root = tmp_path / "tree"
    train_tree(root)
    eval_tree(root)
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
    assert_eval_equal(
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
