"""benchmarks/: a script that needs a missing extra ends with the one line ``pnvlad`` prints for
it and exit status 2 (benchmarks/entry.py), not a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

#: Runs a script as ``python benchmarks/SCRIPT ARGS`` would, with one module made unimportable.
WITHOUT = """
import runpy, sys
sys.modules[sys.argv[1]] = None  # the import fails, as when the package is not installed
script = sys.argv[2]
sys.path.insert(0, str(__import__("pathlib").Path(script).parent))
sys.argv = sys.argv[2:]
runpy.run_path(script, run_name="__main__")
"""


@pytest.mark.parametrize(
    ("script", "args", "feature", "package", "extra"),
    [
        (
            "make_rosbag.py",
            ["--out", "{tmp}/city.bag", "--preset", "tiny"],
            "Writing ROS bags",
            "rosbags",
            "rosbag",
        ),
        (
            "bench_rosbag.py",
            ["--work", "{tmp}"],
            "Writing and reading ROS bags",
            "rosbags",
            "rosbag",
        ),
        ("realism.py", ["--png", "{tmp}/r.png"], "The realism figure", "matplotlib", "plot"),
    ],
)
def test_a_missing_extra_is_one_line_and_status_2(
    tmp_path: Path, script: str, args: list[str], feature: str, package: str, extra: str
) -> None:
    argv = [a.format(tmp=tmp_path) for a in args]
    done = subprocess.run(
        [sys.executable, "-c", WITHOUT, package, str(BENCHMARKS / script), *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr == (
        f"error: {feature} needs the '{package}' package, which is not installed. "
        f"Install it with: pip install 'pnvlad[{extra}]'\n"
    )
    assert list(tmp_path.iterdir()) == []  # it stopped before writing anything
