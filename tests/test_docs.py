"""The README and the docs as a reader meets them: every relative link resolves (the file, and
the heading an anchor names), and every command in a code block runs as written, as far as
``--help`` can tell: a ``pnvlad`` command line with ``--help`` appended is accepted (its
subcommands exist, its options are the command's), a script it names exists."""

from __future__ import annotations

import importlib.metadata
import re
import shlex
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app

REPO = Path(__file__).resolve().parents[1]
#: The references and the README; the results log (docs/results/) records commands as they were
#: run, so only its links are checked.
REFERENCES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
MARKDOWN = [*REFERENCES, *sorted((REPO / "docs" / "results").glob("*.md"))]
#: Fenced blocks in these languages hold no shell commands.
NOT_SHELL = {"json", "python", "text", "yaml"}

FENCE = re.compile(r"^```(\w*)\s*$")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
INLINE_CODE = re.compile(r"`[^`\n]+`")


def _blocks(text: str) -> tuple[str, list[tuple[str, list[str]]]]:
    """The text outside fenced blocks and the blocks (language, lines)."""
    prose, blocks, lang, lines = [], [], None, []
    for line in text.splitlines():
        fence = FENCE.match(line)
        if fence and lang is None:
            lang, lines = fence.group(1), []
        elif line.startswith("```") and lang is not None:
            blocks.append((lang, lines))
            lang = None
        elif lang is not None:
            lines.append(line)
        else:
            prose.append(line)
    return "\n".join(prose), blocks


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped (but ``-`` and
    ``_``), spaces to hyphens."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    prose, _ = _blocks(path.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", prose, re.M)}


def broken_links(path: Path) -> list[str]:
    prose, _ = _blocks(path.read_text())
    broken = []
    for target in LINK.findall(INLINE_CODE.sub("", prose)):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.name}")
    return broken


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(path: Path) -> None:
    assert broken_links(path) == []


def test_the_link_check_sees_a_missing_file_and_a_missing_heading(tmp_path: Path) -> None:
    (tmp_path / "B.md").write_text("# Current figures\n\n## `pnvlad serve` (the server)\n")
    page = tmp_path / "A.md"
    page.write_text(
        "[ok](B.md#current-figures) [ok](B.md#pnvlad-serve-the-server) [gone](C.md)\n"
        "[wrong](B.md#figures) `[in code](D.md)` [web](https://example.org/x)\n"
        "```\n[in a block](E.md)\n```\n"
    )
    assert broken_links(page) == ["C.md: no such file", "B.md#figures: no heading #figures in B.md"]


def commands(path: Path) -> list[list[str]]:
    """The command lines of a file's shell blocks (continuations joined, comments and prompts
    dropped), and, for the README, its inline code that starts with ``pnvlad``."""
    text = path.read_text()
    _, blocks = _blocks(text)
    lines: list[str] = []
    for lang, block in blocks:
        if lang in NOT_SHELL:
            continue
        joined = "\n".join(block).replace("\\\n", " ")
        lines += [line.strip().removeprefix("$ ") for line in joined.splitlines()]
    if path.name == "README.md":
        lines += [code.strip("`") for code in INLINE_CODE.findall(text)]
    out = []
    for line in lines:
        for part in re.split(r"\s*(?:&&|;)\s*", line):
            if re.match(r"(pnvlad|bash|python|pip)\b", part):  # not a diagram or an output
                out.append(shlex.split(part, comments=True))
    return out


def _extras() -> set[str]:
    return set(importlib.metadata.metadata("pnvlad").get_all("Provides-Extra") or [])


def command_problem(words: list[str]) -> str | None:
    """Why ``words`` would not run as the docs say, or None."""
    if words[0] == "pnvlad":
        if re.fullmatch(r"[A-Z_]+", words[1]):  # `pnvlad COMMAND --help`: any command
            return None
        res = CliRunner().invoke(app, [*words[1:], "--help"])
        # Typer draws errors in a box: the message without its frame.
        return " ".join(re.sub(r"[│╭╮╰╯─]", " ", res.output).split()) if res.exit_code else None
    if words[0] == "pip":
        extras = {e for w in words for e in re.findall(r"\.\[([\w,]+)\]", w)}
        missing = {e for group in extras for e in group.split(",")} - _extras()
        return f"no extra {sorted(missing)}" if missing else None
    script = next((w for w in words[1:] if not w.startswith("-")), None)
    if script is None or words[1:2] == ["-m"]:
        return None
    if re.match(r"[\w./-]+\.(py|sh)$", script) and not (REPO / script).is_file():
        return f"no such file {script}"
    return None


@pytest.mark.parametrize("path", REFERENCES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_command_in_a_code_block_runs_as_written(path: Path) -> None:
    problems = {" ".join(w): command_problem(w) for w in commands(path)}
    assert {cmd: why for cmd, why in problems.items() if why} == {}


def test_the_readme_names_the_commands_it_promises() -> None:
    found = {" ".join(w[:2]) for w in commands(REPO / "README.md")}
    assert {"bash scripts/demo.sh", "bash scripts/test.sh", "pnvlad serve"} <= found


def test_the_command_check_refuses_what_would_not_run() -> None:
    assert command_problem(["pnvlad", "index", "build", "-m", "M", "-r", "R", "-o", "O"]) is None
    assert "No such option" in command_problem(["pnvlad", "index", "build", "--no-such"])
    assert "No such command" in command_problem(["pnvlad", "indx", "build"])
    assert command_problem(["pnvlad", "localize", "--rosbag", "B", "--no-progress"]) is None
    assert command_problem(["bash", "scripts/nothing.sh"]) == "no such file scripts/nothing.sh"
    assert command_problem(["pip", "install", "-e", ".[io,nope]"]) == "no extra ['nope']"


def test_every_doc_the_code_names_exists() -> None:
    named = set()
    for folder in ("pnvlad_service", "cli", "benchmarks", "scripts", "tests"):
        for path in (REPO / folder).rglob("*"):
            if path.suffix in (".py", ".sh", ".yaml"):
                named |= set(re.findall(r"\bdocs/[\w/]+\.md", path.read_text()))
    assert named and {n for n in named if not (REPO / n).is_file()} == set()
