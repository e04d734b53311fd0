"""The wheel holds every package of the source tree (pyproject.toml lists them by hand)."""

from __future__ import annotations

from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")

REPO = Path(__file__).resolve().parents[1]


def test_every_library_package_is_listed_in_pyproject() -> None:
    listed = set(
        tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    src = REPO / "pnvlad_service"
    on_disk = {
        ".".join(("pnvlad_service", *d.relative_to(src).parts)).rstrip(".")
        for d in [src, *(p for p in src.rglob("*") if p.is_dir())]
        if (d / "__init__.py").is_file() or any(d.glob("*.yaml"))
    }
    assert on_disk - listed == set(), "packages missing from pyproject.toml"
    assert {p for p in listed if p.startswith("pnvlad_service")} - on_disk == set()


def test_the_shipped_pretrained_models_verify_and_keep_to_the_size_limits() -> None:
    """Every model of the package's catalogue is there with the SHA-256 and size it records,
    each within MAX_MODEL_BYTES and all together within MAX_TOTAL_BYTES (docs/MODEL.md says
    why), and the folder holds nothing the catalogue does not list."""
    from pnvlad_service.models import pretrained

    path = REPO / "pnvlad_service" / "pretrained" / "catalogue.json"
    cat = pretrained.Catalogue.read(path)
    assert cat.path == path
    listed = {"catalogue.json"} | {e.dir for e in cat.entries}
    assert {p.name for p in path.parent.iterdir()} == listed
    for entry in cat.entries:
        assert cat.problems(entry) == [], entry.name
        assert {p.name for p in cat.directory(entry).iterdir()} == set(entry.files)
        assert entry.bytes <= pretrained.MAX_MODEL_BYTES, entry.name
        assert entry.dtype in ("float16", "float32") and entry.kind in pretrained.KINDS
    assert sum(p.stat().st_size for p in path.parent.rglob("*") if p.is_file()) <= (
        pretrained.MAX_TOTAL_BYTES + path.stat().st_size
    )


@pytest.mark.slow
def test_a_built_wheel_carries_the_configs_and_the_pretrained_models(tmp_path: Path) -> None:
    """A wheel built from a copy of the sources (with one stand-in model added to its
    pretrained folder) holds the configurations, the catalogue and every file of the model."""
    import shutil
    import subprocess
    import sys
    import zipfile

    src = tmp_path / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("pnvlad_service", "cli"):
        shutil.copytree(REPO / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    model = src / "pnvlad_service" / "pretrained" / "stand-in"
    model.mkdir()
    for name in ("model.json", "model.safetensors", "model.onnx"):
        (model / name).write_bytes(b"x")
    out = tmp_path / "dist"
    code = "import sys; from setuptools import build_meta as b; print(b.build_wheel(sys.argv[1]))"
    res = subprocess.run(
        [sys.executable, "-c", code, str(out)], cwd=src, capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr[-2000:]
    (wheel,) = out.glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {
        f"pnvlad_service/configs/{p.name}" for p in (REPO / "pnvlad_service/configs").glob("*.yaml")
    }
    assert configs and configs <= names
    assert "pnvlad_service/pretrained/catalogue.json" in names
    assert {
        f"pnvlad_service/pretrained/stand-in/{n}"
        for n in ("model.json", "model.safetensors", "model.onnx")
    } <= names
    assert "pnvlad_service/models/pretrained.py" in names and "pnvlad_cli/model.py" in names
