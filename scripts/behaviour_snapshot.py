"""Behaviour snapshots: show that a refactor left unchanged what users see.

A snapshot is a folder of plain files, one a thing a user can observe, written by the code the
running python imports. Take one before a refactor and one after, on the very same inputs,
and compare them item by item:

    python scripts/behaviour_snapshot.py fixture --out /data/behaviour_fixture    # once
    /before/.venv/bin/python scripts/behaviour_snapshot.py snapshot \\
        --fixture /data/behaviour_fixture --out /data/before
    /after/.venv/bin/python scripts/behaviour_snapshot.py snapshot \\
        --fixture /data/behaviour_fixture --out /data/after
    python scripts/behaviour_snapshot.py compare /data/before /data/after \\
        --allow scripts/behaviour_allowed.txt

Each checkout's own ``.venv/bin/python`` (an editable install of that checkout) decides which
code is snapshotted, wherever the script lies; ``.meta.json`` in the snapshot names that code,
its commit, the date and the durations (files whose name starts with a dot are not compared).
About 2 minutes a snapshot and 2 for the fixture, on 2 busy cores.

``fixture`` (scripts/behaviour_fixture.py) builds the inputs once, with stable commands only
(``pnvlad synth --preset tiny --seed 3``, ``pnvlad train -c compact --max-steps 2``, ``pnvlad
index build``, ``benchmarks/make_rosbag.py``, numpy): the tiny synthetic city; a model trained
two steps; a submap map (``map.index``) and a keyframe map (``keys.index``) of every run but
the first; query clouds of that held-out run (three submaps with their frames' scales, two raw
scans with priors 1.5 m and 3 degrees off their true poses, a 20 m window laid as the map's
windows are); its first 30 scans as a ROS 2 bag (``drive/``: /points, /odom, /ground_truth)
and its first 20 as a KITTI sequence (``kitti/``). ``fixture.json``, written last, lists
every file with its sha256: a snapshot refuses a fixture that is incomplete or changed. The
bundles record the model's and the tree's paths: build the fixture where it stays.

``snapshot`` writes into ``--out`` (new or empty):

- ``openapi.json``: ``GET /openapi.json`` of a real ``pnvlad serve`` (keys sorted);
- ``help/pnvlad[-SUB...].txt``: the ``--help`` of every command and sub-command, found by
  walking the Typer/Click command tree, 100 columns wide, no colour, trailing blanks dropped;
- ``http/map/*.json``, ``http/keys/*.json``: requests (scripts/behaviour_http.py) to two real
  ``pnvlad serve`` on 127.0.0.1, one of the submap map, one of the keyframe map: submaps (JSON,
  a float32 body, with a scale, verify false), windows (``.npy`` and JSON), raw scans (JSON, a
  float64 body), raw scans with a prior (JSON, query parameters, a map run named, off the map),
  batches (JSON, ``.npy``), ``/info``, ``/readyz``, ``/healthz``, and refusals: every rule a
  query can break, malformed JSON, a wrong media type, ``/admin/reload`` off, without a key,
  with a wrong key, with an unreadable body. Each file: the request (its arrays by shape), the
  status, the content type, the answer;
- ``cli/``: ``pnvlad localize SUBMAP --url`` (the table) and ``pnvlad localize SCAN --index
  --preprocess --json`` (in this process, no server);
- ``drives/NAME.csv`` (the rows) and ``drives/NAME.txt`` (the exit status and what was
  printed) of ``pnvlad localize``: ``follow-bag`` (``--rosbag`` against the keyframe server),
  ``follow-bag-index`` (the same bag, in this process: ``--index``), ``follow-kitti``
  (``--kitti``, against the server), ``replay-bag`` (``--per-scan --every 5``) and
  ``replay-windows`` (``--per-scan --window 20`` against the submap server).

Volatile values become ``"<volatile>"``, the key kept (a key that appears or goes is seen):
every value under ``timings_ms``, a reload's ``load_s`` and ``drain_s``, the follow CSV's
``read_ms``, ``odometry_ms``, ``step_ms`` and ``server_ms``, milliseconds and rates in printed
lines and a follow's own duration; package versions (``torch 2.13.0+cpu`` -> ``torch
<version>``, OpenAPI's ``info.version``); the servers' ports become ``<port>``, the fixture's
and the work folder's paths ``<fixture>`` and ``<work>``. Every process runs with 2 threads
(``OMP_NUM_THREADS``, ``PNVLAD_THREADS``; registration's 2 even when crowded), 100 columns, no
colour, and without the caller's ``PNVLAD_*`` variables. Everything else is kept as the code
wrote it, floats as Python prints them. Two snapshots of one code are then the same but for
the last digits of what registration derives from its Hessian (summed on two threads in a
changing order: the ``constraint``, ``sigma_m``, the covariance, the ``confidence``, about
1e-13 relative apart): ``compare`` takes numbers within 1e-9 (relative) as equal and says so
(``same~``); integers, words and printed lines compare exactly.

``compare A B`` (scripts/behaviour_compare.py) prints one line an item (``same``, ``same~``,
``DIFFERS``, ``ONLY IN A``, ``ONLY IN B``, ``allowed``) and a unified diff of each difference
(numbers rounded to 9 digits; a CSV: its header's change, then the rows of the columns both
have), and exits 1 when an item differs that the ``--allow`` file does not name, else 0 (2: a
usage error). The allow file holds one item a line, a glob of snapshot paths, then the reason
(required); ``ITEM:columns`` allows only a CSV's columns to be added or reordered, the values of
the columns both have still compared::

    # item                           reason
    openapi.json                     the one-point query's limit stated in the schema
    drives/replay-bag.csv:columns    one row type for replay and follow: columns added
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from behaviour_compare import compare, read_allowed
from behaviour_fixture import FIXED_ENV, build_fixture, child_env, read_fixture
from behaviour_http import ADMIN_KEY, Server, asks, describe, encode, request

VOLATILE = "<volatile>"
#: Keys whose values are times (JSON answers).
VOLATILE_KEYS = {"timings_ms", "load_s", "drain_s", "uptime_s"}
#: Columns of drive CSVs that are times.
VOLATILE_COLUMNS = {"read_ms", "odometry_ms", "step_ms", "server_ms"}
#: Printed figures that are times or rates (a follow's own speed, a stage's milliseconds): the
#: number is replaced, the words kept. Times of the drive itself ("first fix at scan 3 (12.0 m,
#: 1.2 s)") are not volatile and stay.
VOLATILE_TEXT = [
    (re.compile(r"\d+(\.\d+)?(?= ?(ms|scans/s|x real time|req/s)\b)"), VOLATILE),
    (re.compile(r"(?<= scans in )\d+(\.\d+)?(?= s \()"), VOLATILE),
    (re.compile(r"(?<=mean ms: ).*"), VOLATILE),
    (
        re.compile(r"\b(torch|onnxruntime|faiss|numpy|pnvlad) \d+\.\d+(\.\d+)?[\w.+-]*"),
        r"\1 <version>",
    ),
]


# --------------------------------------------------------------------------------------------
# normalising what is volatile
# --------------------------------------------------------------------------------------------


@dataclass
class Places:
    """What differs between two snapshots of one code, made the same: the fixture's and the
    work folder's paths, the servers' ports (``127.0.0.1:PORT``), times, package versions."""

    fixture: Path
    work: Path
    ports: list[int] = field(default_factory=list)

    def text(self, s: str) -> str:
        s = s.replace(str(self.work), "<work>").replace(str(self.fixture), "<fixture>")
        for port in self.ports:
            s = s.replace(f"127.0.0.1:{port}", "127.0.0.1:<port>")
        for pattern, repl in VOLATILE_TEXT:
            s = pattern.sub(repl, s)
        return s

    def json(self, value: Any, key: str | None = None) -> Any:
        """``value`` with times replaced (the keys kept) and paths and versions normalised."""
        if key in VOLATILE_KEYS:
            if isinstance(value, dict):
                return {k: VOLATILE if v is not None else None for k, v in value.items()}
            return VOLATILE if value is not None else None
        if isinstance(value, dict):
            return {k: self.json(v, k) for k, v in value.items()}
        if isinstance(value, list):
            return [self.json(v) for v in value]
        if isinstance(value, str):
            return self.text(value)
        return value

    def csv(self, text: str) -> str:
        """A drive CSV with its time columns replaced."""
        rows = list(csv.reader(io.StringIO(text)))
        if not rows:
            return text
        hidden = [i for i, name in enumerate(rows[0]) if name in VOLATILE_COLUMNS]
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(rows[0])
        for row in rows[1:]:
            writer.writerow(
                [VOLATILE if i in hidden and v else self.text(v) for i, v in enumerate(row)]
            )
        return buf.getvalue()


def write_json(path: Path, value: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=2, sort_keys=True, ensure_ascii=False) + "\n")


# --------------------------------------------------------------------------------------------
# snapshot: help
# --------------------------------------------------------------------------------------------


def snapshot_help(out: Path) -> int:
    """help/pnvlad[-SUB...].txt for every command of the Typer app (this process's env is
    FIXED_ENV before typer is imported: typer reads the width once)."""
    import typer
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    runner = CliRunner()
    count = 0

    def walk(cmd: Any, path: list[str]) -> None:
        nonlocal count
        res = runner.invoke(app, [*path, "--help"], prog_name="pnvlad", color=False)
        text = "\n".join(line.rstrip() for line in res.output.splitlines()).strip("\n")
        name = "-".join(["pnvlad", *path])
        status = "" if res.exit_code == 0 else f"[exit {res.exit_code}]\n"
        (out / "help").mkdir(parents=True, exist_ok=True)
        (out / "help" / f"{name}.txt").write_text(status + text + "\n")
        count += 1
        for sub_name in sorted(getattr(cmd, "commands", {})):
            walk(cmd.commands[sub_name], [*path, sub_name])

    walk(typer.main.get_command(app), [])
    return count


def run_asks(servers: dict[str, Server], fixture: Path, q: dict, out: Path, places: Places) -> int:
    """http/SERVER/NAME.json for each request: the request, the status, the answer."""
    todo = asks(fixture, q)
    for ask in todo:
        headers = dict(ask.headers)
        if ask.json is not None:
            body: bytes | None = json.dumps(encode(ask.json)).encode()
            headers["Content-Type"] = "application/json"
            shown: Any = describe(ask.json)
        elif ask.raw is not None:
            headers["Content-Type"], body = ask.raw
            shown = f"<{len(body)} bytes of {ask.raw[0]}>"
        else:
            body, shown = None, None
        status, ctype, answer = request(
            servers[ask.server].url, ask.method, ask.path, body, headers
        )
        try:
            parsed: Any = json.loads(answer)
        except ValueError:
            parsed = answer.decode("utf-8", "replace")
        record = {
            "request": {
                "method": ask.method,
                "path": ask.path,
                "body": shown,
                "headers": {k: "<key>" if k == "Authorization" else v for k, v in headers.items()},
            },
            "status": status,
            "content_type": ctype,
            "answer": places.json(parsed),
        }
        write_json(out / "http" / ask.server / f"{ask.name}.json", record)
    return len(todo)


# --------------------------------------------------------------------------------------------
# snapshot: commands and drives
# --------------------------------------------------------------------------------------------


def run_cli(args: list[str], places: Places) -> str:
    """``pnvlad ARGS``' exit status and stdout, normalised (stderr, the logs, is not kept)."""
    done = subprocess.run(
        [sys.executable, "-m", "pnvlad_cli.main", *args],
        env=child_env(),
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        print(
            f"  note: pnvlad {' '.join(args[:2])} exited {done.returncode}: "
            f"{done.stderr.strip().splitlines()[-1:]}"
        )
    return f"[exit {done.returncode}]\n" + places.text(done.stdout)


def snapshot_commands(
    fixture: Path, record: dict, servers: dict[str, Server], out: Path, places: Places
) -> int:
    """cli/*: ``pnvlad localize`` of a file, from a server and in this process."""
    import numpy as np

    q = record["queries"]
    (out / "cli").mkdir(parents=True, exist_ok=True)
    sub = places.work / "submap0.bin"
    np.load(fixture / q["submaps"][0]["file"]).astype("<f8").tofile(sub)
    scan = places.work / "scan0.npy"
    shutil.copyfile(fixture / q["scans"][0]["file"], scan)
    table = run_cli(["localize", str(sub), "--url", servers["map"].url, "-n", "3"], places)
    (out / "cli" / "localize-submap-url.txt").write_text(table)
    local = ["--index", str(fixture / record["maps"]["keys"]), "--preprocess", "--json"]
    text = run_cli(["localize", str(scan), *local], places)
    status, _, body = text.partition("\n")
    try:
        answer: Any = places.json(json.loads(body))
    except ValueError:
        answer = body
    write_json(out / "cli" / "localize-scan-index.json", {"status": status, "answer": answer})
    return 2


#: The bag's topics: its scans, its odometry.
TOPICS = "--cloud-topic /points --pose-topic /odom"


def snapshot_drives(
    fixture: Path, record: dict, servers: dict[str, Server], out: Path, places: Places
) -> int:
    """drives/NAME.csv (the rows) and drives/NAME.txt (what the command printed)."""
    bag, kitti = record["bag"], record["kitti"]
    keys, submaps = (str(fixture / record["maps"][m]) for m in ("keys", "map"))
    quiet = ["--no-plot", "--no-progress"]
    topics = ["--rosbag", str(fixture / bag["path"]), *TOPICS.split(), "--origin", bag["origin"]]
    truth = ["--truth-topic", "/ground_truth"]
    keys_url = ["--url", servers["keys"].url, "--map", keys]
    map_url = ["--url", servers["map"].url, "--map", submaps]
    placed = ["--origin", kitti["origin"], "--yaw", kitti["yaw"]]
    drives = {
        "follow-bag": [*topics, *truth, *keys_url],
        "follow-bag-index": [*topics, *truth, "--index", keys],
        "follow-kitti": ["--kitti", str(fixture / kitti["path"]), *placed, *keys_url],
        "replay-bag": [*topics, "--per-scan", "--every", "5", *keys_url],
        "replay-windows": [*topics, "--per-scan", "--every", "10", "--window", "20", *map_url],
    }
    (out / "drives").mkdir(parents=True, exist_ok=True)
    for name, args in drives.items():
        raw = places.work / name
        printed = run_cli(["localize", *args, *quiet, "--out", str(raw)], places)
        (out / "drives" / f"{name}.txt").write_text(printed)
        rows = raw.with_name(raw.name + ".csv")
        text = rows.read_text(encoding="utf-8") if rows.is_file() else "(no CSV written)\n"
        (out / "drives" / f"{name}.csv").write_text(places.csv(text))
    return len(drives)


def snapshot(fixture: Path, out: Path, keep_work: bool) -> None:
    """Every item of a snapshot of this checkout's code into ``out`` (see the module)."""
    os.environ.update(FIXED_ENV)
    for k in [k for k in os.environ if k.startswith("PNVLAD_") and k not in FIXED_ENV]:
        del os.environ[k]
    fixture = fixture.resolve()
    record = read_fixture(fixture)
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out}: exists and is not empty")
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="behaviour-snapshot-"))
    places = Places(fixture, work)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    env = dict(record["server_env"])
    keys_env = {**env, "PNVLAD_ADMIN_KEY": ADMIN_KEY}
    servers = {
        "map": Server("map", fixture / record["maps"]["map"], env, work),
        "keys": Server("keys", fixture / record["maps"]["keys"], keys_env, work),
    }
    places.ports = [s.port for s in servers.values()]
    try:
        for s in servers.values():
            s.start()
        counts = {"help": snapshot_help(out)}
        times["help"] = time.perf_counter() - t0
        for s in servers.values():
            s.wait_ready()
        times["servers ready"] = time.perf_counter() - t0
        doc = json.loads(request(servers["map"].url, "GET", "/openapi.json")[2])
        doc.get("info", {})["version"] = "<version>"  # the package's: not the contract
        write_json(out / "openapi.json", doc)
        counts["http"] = run_asks(servers, fixture, record["queries"], out, places)
        times["http"] = time.perf_counter() - t0
        counts["cli"] = snapshot_commands(fixture, record, servers, out, places)
        counts["drives"] = snapshot_drives(fixture, record, servers, out, places)
        times["drives"] = time.perf_counter() - t0
    finally:
        for s in servers.values():
            s.stop()
        if not keep_work:
            shutil.rmtree(work, ignore_errors=True)
    read_fixture(fixture)  # nothing wrote into it
    write_json(out / ".meta.json", meta(fixture, counts, times))
    print(
        f"snapshot: {out}: {counts} in {time.perf_counter() - t0:.0f} s"
        + (f" (work kept: {work})" if keep_work else "")
    )


def meta(fixture: Path, counts: dict, times: dict) -> dict[str, Any]:
    """What a snapshot records of itself (not compared)."""
    import pnvlad_service

    code = Path(pnvlad_service.__file__).resolve().parent

    def git(*args: str) -> str:
        done = subprocess.run(["git", *args], cwd=code, capture_output=True, text=True)
        return done.stdout.strip()

    return {
        "code": str(code),
        "commit": git("rev-parse", "HEAD"),
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
        "fixture": str(fixture),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "items": counts,
        "seconds": {k: round(v, 1) for k, v in times.items()},
    }


# --------------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="behaviour_snapshot.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fixture", help="build the inputs both snapshots use, once")
    f.add_argument("--out", type=Path, required=True, help="fixture folder to create")
    s = sub.add_parser("snapshot", help="snapshot the code this python imports")
    s.add_argument("--fixture", type=Path, required=True, help="a folder `fixture` built")
    s.add_argument("--out", type=Path, required=True, help="snapshot folder (new or empty)")
    s.add_argument("--keep-work", action="store_true", help="keep the raw outputs and logs")
    c = sub.add_parser("compare", help="diff two snapshots; exit 1 on an unallowed difference")
    c.add_argument("a", type=Path, metavar="SNAP_A", help="the snapshot before")
    c.add_argument("b", type=Path, metavar="SNAP_B", help="the snapshot after")
    c.add_argument("--allow", type=Path, help="items expected to differ, each with its reason")
    c.add_argument("--diff-lines", type=int, default=80, help="most diff lines an item")
    args = parser.parse_args(argv)
    if args.command == "fixture":
        build_fixture(args.out.resolve())
        return 0
    if args.command == "snapshot":
        snapshot(args.fixture, args.out.resolve(), args.keep_work)
        return 0
    return compare(args.a, args.b, read_allowed(args.allow), args.diff_lines)


if __name__ == "__main__":
    sys.exit(main())
