"""progress: tqdm's bar on a terminal; plain lines, without carriage returns, anywhere else."""

from __future__ import annotations

import ast
import io
from pathlib import Path

import pytest

from pnvlad_service import progress
from pnvlad_service.progress import tqdm


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_off_a_terminal_each_update_is_a_line_of_its_own() -> None:
    log = io.StringIO()
    for _ in tqdm(range(5), desc="check", unit="run", file=log):
        pass
    lines = log.getvalue().splitlines(keepends=True)
    assert "\r" not in log.getvalue()
    # a line at the start, one at the end (the interval keeps the ones between out)
    assert [line.split(" [")[0] for line in lines] == ["check:   0% 0/5", "check: 100% 5/5"]
    assert all(line.endswith("run/s]\n") for line in lines)


def test_lines_follow_the_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.0)
    log = io.StringIO()
    with tqdm(total=None, desc="bag", unit="scan", file=log) as bar:
        for _ in range(3):
            bar.update()
    got = [line.split(" [")[0] for line in log.getvalue().splitlines()]
    assert got == ["bag: 0scan", "bag: 1scan", "bag: 2scan", "bag: 3scan", "bag: 3scan"]


def test_a_postfix_set_every_step_does_not_write_a_line_each() -> None:
    log = io.StringIO()
    with tqdm(total=50, desc="train", unit="step", file=log) as bar:
        for step in range(50):
            bar.update()
            bar.set_postfix(loss=f"{1 / (step + 1):.4f}")
            bar.set_description("train")
    lines = log.getvalue().splitlines()
    assert len(lines) == 2, lines
    assert lines[-1].startswith("train: 100% 50/50") and "loss=0.0200" in lines[-1]


def test_a_bar_that_does_not_stay_leaves_only_its_first_line() -> None:
    log = io.StringIO()
    with tqdm(total=4, desc="load", file=log, leave=False) as bar:
        bar.update(4)
    assert log.getvalue().splitlines()[0].startswith("load:   0% 0/4")
    assert len(log.getvalue().splitlines()) == 1


def test_on_a_terminal_it_is_tqdms_bar() -> None:
    term = Terminal()
    for _ in tqdm(range(3), desc="t", file=term):
        pass
    assert term.getvalue().startswith("\rt:   0%|") and "| 3/3 [" in term.getvalue()


@pytest.mark.parametrize(("disable", "shown"), [(False, True), (None, True), (True, False)])
def test_disable_none_shows_it_even_in_a_log(disable: bool | None, shown: bool) -> None:
    log = io.StringIO()
    for _ in tqdm(range(2), desc="x", file=log, disable=disable):
        pass
    assert bool(log.getvalue()) is shown


def test_every_bar_of_the_library_is_made_here() -> None:
    """A plain ``tqdm`` import would bring carriage returns back into logs."""
    src = Path(progress.__file__).parent
    direct = []
    for path in src.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            if any(n == "tqdm" or n.startswith("tqdm.") for n in names):
                direct.append(str(path.relative_to(src)))
    assert direct == ["progress.py"]
