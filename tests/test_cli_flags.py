"""One short flag, one meaning: across every `pnvlad` command a short option names the same
long option (-m is always the model, -r the tree root, -c only --config, ...)."""

from __future__ import annotations

from collections import defaultdict

import typer

from pnvlad_cli.main import app


def _commands(cmd, path: str = "pnvlad"):
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _commands(sub, f"{path} {name}")


def test_each_short_flag_means_one_option_everywhere() -> None:
    meanings: dict[str, set[str]] = defaultdict(set)
    where: dict[str, list[str]] = defaultdict(list)
    for path, cmd in _commands(typer.main.get_command(app)):
        for param in cmd.params:
            shorts = [o for o in param.opts if len(o) == 2 and o.startswith("-")]
            longs = tuple(sorted(o for o in param.opts if o.startswith("--")))
            for s in shorts:
                meanings[s].add(" / ".join(longs))
                where[s].append(path)
    clashes = {s: sorted(m) for s, m in meanings.items() if len(m) > 1}
    assert clashes == {}, {s: (m, where[s]) for s, m in clashes.items()}
    # the ones the issue names
    assert meanings["-m"] == {"--checkpoint / --model"}
    assert meanings["-r"] == {"--root"}
    assert meanings["-c"] == {"--config"}


def test_every_command_that_takes_a_model_says_model() -> None:
    for path, cmd in _commands(typer.main.get_command(app)):
        for param in cmd.params:
            if "--checkpoint" in param.opts:
                assert "--model" in param.opts and "-m" in param.opts, path


#: The commands that draw progress bars (minutes on a big tree, a long drive or a bag).
LONG = {
    "pnvlad data check",
    "pnvlad data splits",
    "pnvlad data export-pickles",
    "pnvlad data prepare",
    "pnvlad data import",
    "pnvlad synth",
    "pnvlad train",
    "pnvlad eval",
    "pnvlad index build",
    "pnvlad index add",
    "pnvlad localize",
}


def test_every_long_command_takes_the_same_progress_switch() -> None:
    switches = {}
    for path, cmd in _commands(typer.main.get_command(app)):
        for param in cmd.params:
            if "--progress" in param.opts:
                switches[path] = (*param.opts, *param.secondary_opts, param.default, param.help)
    assert set(switches) == LONG
    assert len(set(switches.values())) == 1
    assert switches["pnvlad localize"][:3] == ("--progress", "--no-progress", True)
