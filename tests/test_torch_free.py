"""Without torch: what needs it says so in one line naming the extra, and what serves does not
import it. Each check runs in a fresh interpreter with ``sys.modules["torch"] = None`` (every
``import torch`` then fails, as where it is not installed)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BLOCK = "import sys; sys.modules['torch'] = None; sys.modules['onnx'] = None\n"


def run_without_torch(code: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``code`` in a new interpreter that cannot import torch (nor onnx)."""
    return subprocess.run(
        [sys.executable, "-c", BLOCK + textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=timeout,
    )


def cli_without_torch(*argv: str) -> subprocess.CompletedProcess:
    code = """
        import sys
        from pnvlad_cli.main import app
        sys.argv = ["pnvlad", *sys.argv[1:]]
        app()
    """
    return run_without_torch(code, *argv)


def test_the_server_and_the_cli_import_without_torch() -> None:
    r = run_without_torch(
        """
        import pnvlad_service.server.app, pnvlad_service.models.onnx_encoder
        import pnvlad_service.models.runtimes, pnvlad_service.localization.query.localizer
        import pnvlad_cli.main
        print("ok")
        """
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"


@pytest.mark.parametrize(
    ("argv", "command"),
    [
        (["train", "-c", "cpu", "--root", "r", "--splits", "r/s.json", "-o", "o"], "pnvlad train"),
        (["model", "export", "MODEL"], "pnvlad model export"),
        (["model", "info", "MODEL"], "pnvlad model info"),
    ],
)
def test_what_needs_torch_says_so_in_one_line(
    argv: list[str], command: str, tmp_path: Path
) -> None:
    from pnvlad_service.models.config import ModelConfig

    model = tmp_path / "m"
    model.mkdir()
    doc = {"format": "pnvlad-model", "version": 1, "model": ModelConfig.compact().model_dump()}
    (model / "model.json").write_text(json.dumps(doc))
    (model / "model.safetensors").write_bytes(b"\0" * 16)
    (tmp_path / "r").mkdir()
    argv = [str(model) if a == "MODEL" else str(tmp_path / a) if "/" in a else a for a in argv]
    r = cli_without_torch(*argv)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (
        f"error: {command} needs the 'torch' package, which is not installed. "
        "Install it with: pip install 'pnvlad[torch]'"
    )


def test_index_add_without_torch_embeds_on_model_onnx(tmp_path: Path) -> None:
    """A robot's computer without torch adds its survey run to the map (then reloads the
    server): `pnvlad index add` embeds with ONNX Runtime, and the vectors are torch's."""
    pytest.importorskip("onnx")
    from pnvlad_service.index.build import add_to_bundle, build_bundle
    from pnvlad_service.index.bundle import IndexBundle
    from pnvlad_service.models.onnx_export import export_onnx
    from tests.index.helpers import RUNS, make_checkpoint, make_tree

    tree = make_tree(tmp_path / "tree")
    ckpt = make_checkpoint(tmp_path / "ckpt")
    export_onnx(ckpt)
    for name in ("torch.index", "onnx.index"):
        build_bundle(tmp_path / name, ckpt, tree, runs=[RUNS[0]], progress=False)
    add_to_bundle(tmp_path / "torch.index", ckpt, tree, runs=[RUNS[1]], progress=False)
    r = cli_without_torch("-q", "index", "add", str(tmp_path / "onnx.index"), "-m", str(ckpt),
                          "-r", str(tree), "--run", RUNS[1], "--no-progress")  # fmt: skip
    assert r.returncode == 0, r.stderr
    a, b = (IndexBundle.load(tmp_path / n) for n in ("torch.index", "onnx.index"))
    assert a.count == b.count
    va = a.index.reconstruct_n(0, a.count)
    vb = b.index.reconstruct_n(0, b.count)
    assert abs(va - vb).max() < 1e-5
