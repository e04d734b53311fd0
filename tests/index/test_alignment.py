"""A bundle records that its map is aligned: ``pnvlad index build`` of a tree that ``pnvlad map
align`` wrote keeps the sha256 of its ``align_report.json`` in the manifest's ``map`` entry; a
recorded tree, a run the alignment lacks, or runs added from elsewhere leave it unrecorded."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.index.build import add_to_bundle, build_bundle
from pnvlad_service.index.manifest import Manifest, MapRecord
from pnvlad_service.index.tree_records import ALIGN_REPORT, ALIGNED_POSES


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_file_names_are_map_aligns() -> None:
    from pnvlad_service.mapping.align import REPORT
    from pnvlad_service.mapping.relay import ALIGNED_POSES as RELAY_POSES

    assert (ALIGN_REPORT, ALIGNED_POSES) == (REPORT, RELAY_POSES)


def test_a_bundle_of_an_aligned_tree_records_its_alignment(tiny_aligned: dict) -> None:
    manifest = Manifest.read(tiny_aligned["keys"])
    want = _sha256(tiny_aligned["tree"] / ALIGN_REPORT)
    assert manifest.map_record.alignment == want and manifest.map_record.aligned
    on_disk = json.loads((tiny_aligned["keys"] / "manifest.json").read_text())
    assert on_disk["map"]["alignment"] == want


def test_a_bundle_of_the_recorded_tree_does_not(tiny_maps: dict) -> None:
    manifest = Manifest.read(tiny_maps["keys"])
    assert manifest.map_record.alignment is None and not manifest.map_record.aligned
    on_disk = json.loads((tiny_maps["keys"] / "manifest.json").read_text())
    assert "alignment" not in on_disk["map"]  # the manifests made before stay as they were


def test_a_run_the_alignment_lacks_leaves_it_unrecorded(
    tiny_aligned: dict, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    tree = tmp_path / "tree"
    shutil.copytree(tiny_aligned["tree"], tree)
    runs = sorted(p.name for p in (tree / "business").iterdir() if p.is_dir())
    (tree / "business" / runs[-1] / ALIGNED_POSES).unlink()  # a run added after the alignment
    with caplog.at_level(logging.WARNING):
        build_bundle(tmp_path / "b.index", tiny_aligned["ckpt"], tree, layout="keyframe",
                     progress=False)  # fmt: skip
    assert Manifest.read(tmp_path / "b.index").map_record.alignment is None
    assert f"business/{runs[-1]}" in caplog.text and ALIGNED_POSES in caplog.text


def test_runs_added_from_elsewhere_end_it_and_of_the_alignment_keep_it(
    tiny_aligned: dict, tiny: Path, tmp_path: Path
) -> None:
    runs = sorted(p.name for p in (tiny / "business").iterdir() if p.is_dir())
    ckpt, tree = tiny_aligned["ckpt"], tiny_aligned["tree"]
    want = _sha256(tree / ALIGN_REPORT)
    same = tmp_path / "same.index"
    build_bundle(same, ckpt, tree, runs=runs[1:], layout="keyframe", progress=False)
    add_to_bundle(same, ckpt, tree, runs=runs[:1], layout="keyframe", progress=False)
    assert Manifest.read(same).map_record.alignment == want
    other = tmp_path / "other.index"
    build_bundle(other, ckpt, tree, runs=runs[1:], layout="keyframe", progress=False)
    add_to_bundle(other, ckpt, tiny, runs=runs[:1], layout="keyframe", progress=False)
    got = Manifest.read(other)
    assert got.map_record.alignment is None and got.count == Manifest.read(same).count


@pytest.mark.parametrize("bad", ["abc", 5, "g" * 64, "A" * 64])
def test_a_malformed_alignment_is_refused_naming_the_file(bad: object) -> None:
    with pytest.raises(InputError, match="alignment") as exc:
        MapRecord.from_json({"kind": "keyframe", "alignment": bad}, "b/manifest.json")
    assert "b/manifest.json" in str(exc.value)
    good = MapRecord.from_json({"kind": "keyframe", "alignment": "0" * 64})
    assert MapRecord.from_json(good.to_json()) == good


def test_index_info_says_whether_the_map_is_aligned(tiny_aligned: dict, tiny_maps: dict) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    want = _sha256(tiny_aligned["tree"] / ALIGN_REPORT)[:16]
    res = CliRunner().invoke(app, ["index", "info", str(tiny_aligned["keys"])])
    assert res.exit_code == 0 and f"aligned (pnvlad map align, report sha256 {want}" in res.output
    res = CliRunner().invoke(app, ["index", "info", str(tiny_maps["keys"])])
    assert res.exit_code == 0 and "not aligned" in res.output
