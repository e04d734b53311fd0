"""scripts/behaviour_snapshot.py compare, on small snapshots written here (the fixture and a
real snapshot take minutes: scripts/behaviour_snapshot.py says how to make them): equal
snapshots pass, a difference fails and is shown, the allow list is honoured (reasons
required), numbers compare within the stated tolerance and integers exactly; and the
snapshot's normalisation of volatile values."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
SCRIPT = SCRIPTS / "behaviour_snapshot.py"

ANSWER = {
    "matches": [{"rank": 1, "timestamp": 1772813593000000, "distance": 0.024552427232265472}],
    "verified": True,
    "timings_ms": {"embed": "<volatile>"},
}
ROWS = "scan,timestamp,state,sigma_m,step_ms\n0,1772813593000000,searching,,<volatile>\n"
ROWS += "1,1772813593399181,tracking,1.074112,<volatile>\n"
SUBMAP, FOLLOW = "http/map/submap.json", "drives/follow-bag.csv"


def write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


def snap(root: Path, changes: dict[str, str] | None = None) -> Path:
    """A snapshot of four items (and the meta file), ``changes`` by path."""
    files = {
        "openapi.json": json.dumps({"paths": {"/localize": {}}}, indent=2),
        "help/pnvlad-serve.txt": "Usage: pnvlad serve [OPTIONS]\n",
        "http/map/submap.json": json.dumps({"status": 200, "answer": ANSWER}, indent=2),
        "drives/follow-bag.csv": ROWS,
        ".meta.json": json.dumps({"date": str(root)}),
    }
    return write(root, {**files, **(changes or {})})


def compare(a: Path, b: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), "compare", str(a), str(b), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_equal_snapshots_pass_and_the_meta_file_is_not_compared(tmp_path: Path) -> None:
    done = compare(snap(tmp_path / "a"), snap(tmp_path / "b"))
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert lines[-1] == "4 items: 0 differ"
    assert "same      http/map/submap.json" in lines and ".meta" not in done.stdout


def test_a_difference_fails_names_the_item_and_shows_the_diff(tmp_path: Path) -> None:
    changed = {**ANSWER, "verified": False}
    b = snap(tmp_path / "b", {SUBMAP: json.dumps({"status": 200, "answer": changed})})
    done = compare(snap(tmp_path / "a"), b)
    assert done.returncode == 1
    assert "DIFFERS   http/map/submap.json" in done.stdout
    assert '-    "verified": true' in done.stdout and '+    "verified": false' in done.stdout
    assert done.stdout.splitlines()[-1] == "4 items: 1 differ (not allowed)"


def test_an_item_only_in_one_snapshot_fails(tmp_path: Path) -> None:
    b = snap(tmp_path / "b", {"help/pnvlad-localize.txt": "Usage: pnvlad localize\n"})
    done = compare(snap(tmp_path / "a"), b)
    assert done.returncode == 1
    assert "ONLY IN B help/pnvlad-localize.txt" in done.stdout


def test_the_allow_list_is_honoured_with_its_reason(tmp_path: Path) -> None:
    a = snap(tmp_path / "a")
    b = snap(tmp_path / "b", {"openapi.json": "{}", "help/pnvlad-serve.txt": "Usage: x\n"})
    allow = write(tmp_path, {"allowed.txt": "# item reason\nopenapi.json  the rules stated\n"})
    done = compare(a, b, "--allow", str(allow / "allowed.txt"))
    assert done.returncode == 1  # the help is not allowed
    assert "allowed   openapi.json: differs (the rules stated)" in done.stdout
    assert "DIFFERS   help/pnvlad-serve.txt" in done.stdout
    (allow / "allowed.txt").write_text("openapi.json  the rules\nhelp/*  new words\nnone  x\n")
    done = compare(a, b, "--allow", str(allow / "allowed.txt"))
    assert done.returncode == 0, done.stdout
    assert "allowed   help/pnvlad-serve.txt: differs (new words)" in done.stdout
    assert "note: allowed but not needed: none" in done.stdout


def test_an_allowed_item_needs_a_reason(tmp_path: Path) -> None:
    write(tmp_path, {"allowed.txt": "openapi.json\n"})
    done = compare(snap(tmp_path / "a"), snap(tmp_path / "b"), "--allow", f"{tmp_path}/allowed.txt")
    assert done.returncode == 2
    assert (
        done.stderr == f"error: {tmp_path}/allowed.txt:1: 'openapi.json' needs a reason after it\n"
    )


def test_columns_allows_added_columns_but_not_changed_values(tmp_path: Path) -> None:
    a = snap(tmp_path / "a")
    added = (
        "scan,timestamp,state,kind,sigma_m,step_ms\n0,1772813593000000,searching,scan,,<volatile>\n"
    )
    added += "1,1772813593399181,tracking,scan,1.074112,<volatile>\n"
    b = snap(tmp_path / "b", {FOLLOW: added})
    allow = write(tmp_path, {"ok.txt": "drives/follow-bag.csv:columns  one row type\n"})
    done = compare(a, b, "--allow", str(allow / "ok.txt"))
    assert done.returncode == 0, done.stdout
    assert "allowed   drives/follow-bag.csv: differs (one row type)" in done.stdout
    assert "columns only in B: kind" in done.stdout
    c = snap(tmp_path / "c", {FOLLOW: added.replace("tracking", "lost")})
    done = compare(a, c, "--allow", str(allow / "ok.txt"))
    assert done.returncode == 1
    assert "DIFFERS   drives/follow-bag.csv" in done.stdout
    assert "-1,1772813593399181,tracking,1.074112,<volatile>" in done.stdout
    assert "+1,1772813593399181,lost,1.074112,<volatile>" in done.stdout


@pytest.mark.parametrize(
    ("distance", "timestamp", "sigma", "line"),
    [
        (0.024552427232265472, 1772813593000000, "1.074112", f"same      {SUBMAP}"),
        # 1e-15 and 1e-13 relative: registration's thread noise
        (0.024552427232265496, 1772813593000000, "1.0741120000001", f"same~     {SUBMAP}"),
        (0.024552427532265472, 1772813593000000, "1.074112", f"DIFFERS   {SUBMAP}"),  # 1e-8
        (0.024552427232265472, 1772813593000001, "1.074112", f"DIFFERS   {SUBMAP}"),  # integers
    ],
)
def test_numbers_compare_within_the_tolerance_and_integers_exactly(
    tmp_path: Path, distance: float, timestamp: int, sigma: str, line: str
) -> None:
    match = {**ANSWER["matches"][0], "distance": distance, "timestamp": timestamp}
    body = json.dumps({"status": 200, "answer": {**ANSWER, "matches": [match]}}, indent=2)
    rows = ROWS.replace("1.074112", sigma)
    done = compare(snap(tmp_path / "a"), snap(tmp_path / "b", {SUBMAP: body, FOLLOW: rows}))
    assert line in done.stdout.splitlines() or f"{line} (numbers within 1e-09)" in done.stdout
    assert done.returncode == (1 if line.startswith("DIFFERS") else 0)
    if sigma != "1.074112":
        assert f"same~     {FOLLOW} (numbers within 1e-09)" in done.stdout.splitlines()


def test_volatile_values_are_normalised_and_the_rest_kept(tmp_path: Path) -> None:
    sys.path.insert(0, str(SCRIPTS))
    try:
        from behaviour_snapshot import Places
    finally:
        sys.path.remove(str(SCRIPTS))
    places = Places(fixture=tmp_path / "fix", work=tmp_path / "work", ports=[41234])
    answer = {
        "timings_ms": {"embed": 4.9, "verify": None},
        "runtime": "torch 2.13.0+cpu, 2 threads",
        "index": f"{tmp_path}/fix/keys.index",
        "url": "http://127.0.0.1:41234/localize",
        "score": 0.19900497512437812,
    }
    assert places.json(answer) == {
        "timings_ms": {"embed": "<volatile>", "verify": None},
        "runtime": "torch <version>, 2 threads",
        "index": "<fixture>/keys.index",
        "url": "http://127.0.0.1:<port>/localize",
        "score": 0.19900497512437812,
    }
    line = (
        "follow: 30 scans in 13.1 s (30.5 scans/s, 12.33x real time); first fix at scan 3 "
        "(12.0 m, 1.2 s); search 0.19 ms"
    )
    assert places.text(line) == (
        "follow: 30 scans in <volatile> s (<volatile> scans/s, <volatile>x real time); first "
        "fix at scan 3 (12.0 m, 1.2 s); search <volatile> ms"
    )
    rows = "scan,step_ms,server_ms,reason\n0,12.5,,not verified\n"
    assert places.csv(rows) == "scan,step_ms,server_ms,reason\n0,<volatile>,,not verified\n"
