"""The stages import one way (docs/ARCHITECTURE.md), and no module imports itself back through
others, inside a stage or across: a new import against the flow fails here."""

from __future__ import annotations

import ast
import re
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "pnvlad_service"
ARCHITECTURE = SRC.parent / "docs" / "ARCHITECTURE.md"

#: The stages each stage may import (besides SHARED and the package's __version__).
ALLOWED: dict[str, set[str]] = {
    "io": set(),
    "preprocess": {"io"},
    "data": {"io", "preprocess"},
    "synth": {"io", "preprocess", "data"},
    "models": set(),
    "index": {"io", "preprocess", "data", "models"},
    "localization": {"io", "preprocess", "data", "models", "index"},
    "evaluation": {"io", "preprocess", "data", "models", "index", "localization"},
    "training": {"io", "data", "models", "evaluation"},
    "server": {"io", "localization"},
    "mapping": {"io", "preprocess", "data", "models", "index", "localization"},
}
SHARED = {"errors", "fileio", "extras", "progress", "configs"}
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


#: Inside a stage split by job: the packages of the stage each package may import. In
#: localization/ verification knows nothing of queries or drives (the query path hands it
#: clouds and ids), the query path nothing of drives, and a drive asks queries and reads
#: priors; the package's own ``__init__`` only names them.
INSIDE: dict[str, dict[str, set[str]]] = {
    "localization": {
        "verify": set(),
        "query": {"verify"},
        "outputs": set(),
        "drive": {"query", "verify", "outputs"},
    },
}


def test_packages_inside_a_stage_import_one_way() -> None:
    wrong = []
    for stage, packages in INSIDE.items():
        for package, allowed in packages.items():
            for path in (SRC / stage / package).rglob("*.py"):
                for name in _imports(path):
                    parts = name.split(".")
                    inside = parts[:2] == ["pnvlad_service", stage] and len(parts) > 2
                    if inside and parts[2] not in (package, *allowed):
                        wrong.append(f"{path.relative_to(SRC)} imports {name}")
    assert wrong == []


def test_every_package_inside_a_split_stage_is_listed() -> None:
    for stage, packages in INSIDE.items():
        found = {p.name for p in (SRC / stage).iterdir() if (p / "__init__.py").is_file()}
        modules = {p.name for p in (SRC / stage).glob("*.py")}
        assert (found, modules) == (set(packages), {"__init__.py"})


def test_the_shared_modules_and_the_client_stand_apart() -> None:
    """The shared modules import none of the stages; the HTTP client is for users, the CLI,
    the demo and the benchmarks: the library never imports it (a drive is handed an ``Ask``),
    and it imports only ``data`` (the window a caller accumulates), never the server's side
    (no torch, FAISS or FastAPI behind ``from pnvlad_service.client import ...``); nothing in
    the library imports the CLI."""
    wrong = []
    for name in SHARED - {"configs"}:
        path = SRC / f"{name}.py"
        for imported in _imports(path):
            parts = imported.split(".")
            if parts[0] == "pnvlad_service" and len(parts) > 1 and parts[1] not in SHARED:
                wrong.append(f"{name}.py imports {imported}")
    for imported in _imports(SRC / "client.py"):
        parts = imported.split(".")
        stage = parts[1] if parts[0] == "pnvlad_service" else None
        if stage not in (None, *SHARED, "data") or parts[0] in (*WEB, "torch", "faiss"):
            wrong.append(f"client.py imports {imported}")
    for path in SRC.rglob("*.py"):
        for imported in _imports(path):
            if imported.startswith(("pnvlad_service.client", "pnvlad_cli")):
                wrong.append(f"{path.relative_to(SRC)} imports {imported}")
    assert wrong == []


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path) -> dict[str, set[str]]:
    """Each module of the package at ``root`` -> the package's modules it imports, wherever the
    import stands (top level, inside a function, under ``TYPE_CHECKING``). ``from p import x``
    counts as importing the module ``p.x`` when there is one, else ``p``; relative imports are
    resolved."""
    paths = {_module_name(p, root): p for p in root.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for me, path in paths.items():
        package = me if path.name == "__init__.py" else me.rpartition(".")[0]
        names: list[str] = []
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                names += [
                    f"{base}.{a.name}" if f"{base}.{a.name}" in paths else base for a in node.names
                ]
        graph[me] = {n for n in names if n in paths and n != me}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every group of modules that import one another (strongly connected components of more
    than one module), each sorted, the groups sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(groups)


def test_no_module_imports_itself_back() -> None:
    assert import_cycles(import_graph(SRC)) == []


def test_the_cycle_check_sees_deferred_relative_and_type_checking_imports(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "stage").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "stage/__init__.py": "",
        "stage/a.py": "from pkg.stage.b import f\n",
        "stage/b.py": "def f():\n    from pkg.stage import a\n",  # back inside a function
        "stage/c.py": "from . import d\n",
        "stage/d.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .c import x\n",
        "e.py": "import pkg.stage.a\nfrom pkg import __version__\n",  # one way: no cycle
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    graph = import_graph(pkg)
    assert graph["pkg.e"] == {"pkg.stage.a", "pkg"}
    assert import_cycles(graph) == [["pkg.stage.a", "pkg.stage.b"], ["pkg.stage.c", "pkg.stage.d"]]


def table_modules(text: str) -> list[str]:
    """The modules a table's first column names (`` `path.py` `` cells), in order."""
    cells = (line.split("|")[1] for line in text.splitlines() if line.startswith("| `"))
    return [name for cell in cells for name in re.findall(r"`([^`]+)`", cell)]


def test_the_architecture_lists_every_module_once() -> None:
    """docs/ARCHITECTURE.md's module table names each module of the package (``__init__``
    aside) once, by its path under ``pnvlad_service/``, and no module that is gone."""
    listed = table_modules(ARCHITECTURE.read_text())
    modules = {str(p.relative_to(SRC)) for p in SRC.rglob("*.py") if p.name != "__init__.py"}
    twice = sorted({m for m in listed if listed.count(m) > 1})
    assert (sorted(modules - set(listed)), sorted(set(listed) - modules), twice) == ([], [], [])


def test_the_table_check_reads_the_first_column_only() -> None:
    text = "| module | job |\n|---|---|\n| `a.py`, `b/c.py` | reads `d.py` |\n| **b/** | x |\n"
    assert table_modules(text) == ["a.py", "b/c.py"]
