"""The stages import one way (docs/ARCHITECTURE.md): a new import against the flow fails here."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "pnvlad_service"

#: The stages each stage may import (besides errors, fileio, extras and the package's __version__).
ALLOWED: dict[str, set[str]] = {
    "io": set(),
    "data": {"io"},
    "synth": {"io", "data"},
    "models": set(),
    "evaluation": {"io", "data", "models"},
    "training": {"io", "data", "models", "evaluation"},
    "index": {"io", "data", "models"},
    "localization": {"io", "data", "models", "evaluation", "index"},
    "server": {"io", "localization"},
}
SHARED = {"errors", "fileio", "extras", "configs"}
WEB = ("fastapi", "starlette", "uvicorn")


def _imports(path: Path) -> list[str]:
    out: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "pnvlad_service":
                out += [f"pnvlad_service.{a.name}" for a in node.names]
            else:
                out.append(node.module)
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names]
    return out


def test_stages_import_only_the_stages_before_them() -> None:
    wrong = []
    for stage, allowed in ALLOWED.items():
        for path in (SRC / stage).rglob("*.py"):
            for name in _imports(path):
                parts = name.split(".")
                if parts[0] == "pnvlad_service" and len(parts) > 1:
                    dst = parts[1]
                    if dst not in (stage, "__version__", *SHARED, *allowed):
                        wrong.append(f"{path.relative_to(SRC)} imports {name}")
                elif parts[0] in WEB and stage != "server":
                    wrong.append(f"{path.relative_to(SRC)} imports {name}")
    assert wrong == []


def test_every_stage_is_listed() -> None:
    stages = {p.name for p in SRC.iterdir() if (p / "__init__.py").is_file()}
    assert stages == set(ALLOWED)
