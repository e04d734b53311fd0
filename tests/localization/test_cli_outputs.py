"""`pnvlad localize --rosbag ... --foxglove --mcap --ros2-bag --trajectories` following the tiny
city's held-out run against a real `pnvlad serve` on 127.0.0.1: a WebSocket client speaking
Foxglove's protocol connects while the bag plays and receives every advertised channel; each
file is read back by an independent reader and compared with the CSV; a port in use, an
unwritable output and a zone that cannot be parsed are one error line each, exit 2, and the CSV
complete."""

from __future__ import annotations

import csv
import json
import math
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.localization.drive.rows import COLUMNS
from pnvlad_service.localization.outputs.step import COVARIANCE_COLUMNS, from_upper_triangle
from tests.index.helpers import free_port
from tests.localization.test_cli_follow import SCANS, FirstScans
from tests.server.test_app import start_server, stop_server

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
pytest.importorskip("rosbags")

#: What the live view advertises.
TOPICS = {
    "/tf", "/pnvlad/map/entries", "/pnvlad/map/cloud", "/pnvlad/scan", "/pnvlad/pose",
    "/pnvlad/pose/covariance", "/pnvlad/truth", "/pnvlad/path", "/pnvlad/truth/path",
    "/pnvlad/state", "/pnvlad/fix",
}  # fmt: skip


@pytest.fixture(scope="module")
def drive(tiny_maps: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    sim = simulated_drive(get_preset("tiny"), 0, 0, 3)  # the tiny fixture's run 0, held out
    east, north = (float(v) for v in sim.world.origin)
    sub = FirstScans(sim, SCANS)
    path = tmp_path_factory.mktemp("outputs") / "run0"
    write_drive_bag(sub, path, origin_ne=(north, east), truth=sub.true_poses)
    port = free_port()
    env = {"PNVLAD_RERANK": "100", "PNVLAD_VERIFY_THRESHOLD": "0.04", "PNVLAD_PRIOR_MAX_SIGMA": "0"}
    proc = start_server(tiny_maps["keys"], port, env)
    yield {"bag": path, "origin": f"{north!r},{east!r}", "url": f"http://127.0.0.1:{port}"}
    stop_server(proc)


def follow_args(drive: dict, tiny_maps: dict, out: Path) -> list[str]:
    return ["localize", "--rosbag", str(drive["bag"]), "--cloud-topic", "/points",
            "--pose-topic", "/odom", "--truth-topic", "/ground_truth", "--origin",
            drive["origin"], "--url", drive["url"], "--map", str(tiny_maps["keys"]), "--out",
            str(out), "--no-progress"]  # fmt: skip


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


class Watcher(threading.Thread):
    """A Foxglove WebSocket client (``foxglove.sdk.v1``): connects as soon as the port opens,
    subscribes to every channel advertised, counts the messages of each topic."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.advertised: dict[int, str] = {}
        self.schemas: dict[str, str] = {}
        self.received: dict[str, int] = {}
        self.first_state: dict | None = None
        self.error: Exception | None = None

    def run(self) -> None:
        from websockets.sync.client import connect

        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                ws = connect(
                    f"ws://127.0.0.1:{self.port}",
                    subprotocols=["foxglove.sdk.v1"],
                    open_timeout=2,
                    max_size=None,
                )  # the map's cloud is megabytes
            except OSError:
                time.sleep(0.01)
                continue
            with ws:
                self.listen(ws)
            return
        self.error = TimeoutError("the live view never opened")

    def listen(self, ws: object) -> None:
        from websockets.exceptions import ConnectionClosed

        subscriptions: dict[int, str] = {}
        try:
            while True:
                frame = ws.recv(timeout=60)  # type: ignore[attr-defined]
                if isinstance(frame, str):
                    doc = json.loads(frame)
                    if doc["op"] == "advertise":
                        subs = []
                        for ch in doc["channels"]:
                            self.advertised[ch["id"]] = ch["topic"]
                            self.schemas[ch["topic"]] = ch["schemaName"]
                            subscriptions[len(subscriptions) + 1] = ch["topic"]
                            subs.append({"id": len(subscriptions), "channelId": ch["id"]})
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))  # type: ignore[attr-defined]
                    continue
                if frame[0] == 1:  # message data: op, subscription id, log time, payload
                    (sub,) = struct.unpack_from("<I", frame, 1)
                    topic = subscriptions[sub]
                    self.received[topic] = self.received.get(topic, 0) + 1
                    if topic == "/pnvlad/state" and self.first_state is None:
                        self.first_state = json.loads(frame[13:])
        except ConnectionClosed:
            pass  # the drive ended: the view stopped
        except Exception as exc:  # reported by the test
            self.error = exc


def test_follow_live_and_to_files(drive: dict, tiny_maps: dict, tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    from pnvlad_service.localization.outputs.mcap_track import plot_mcap, read_track

    evo = pytest.importorskip("evo.tools.file_interface")
    pytest.importorskip("pyproj")  # the zone's latitude and longitude (the geo extra)
    port = free_port()
    out = tmp_path / "run0"
    watcher = Watcher(port)
    watcher.start()
    args = [*follow_args(drive, tiny_maps, out), "--foxglove", f"127.0.0.1:{port}", "--mcap",
            f"{out}.mcap", "--ros2-bag", f"{out}_ros2", "--trajectories", str(out),
            "--utm-zone", "32U"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    watcher.join(30)
    assert res.exit_code == 0, res.output
    assert watcher.error is None, watcher.error
    # The live view: every channel advertised and at least one message of each.
    assert set(watcher.advertised.values()) == TOPICS
    assert set(watcher.received) == TOPICS, watcher.received
    assert watcher.schemas["/pnvlad/pose"] == "foxglove.PoseInFrame"
    assert watcher.first_state is not None and watcher.first_state["state"] in (
        "searching",
        "tracking",
        "lost",
    )
    rows = read_csv(Path(f"{out}.csv"))
    assert tuple(rows[0]) == COLUMNS["tracked"] and len(rows) == SCANS
    assert tuple(rows[0])[:30] == COLUMNS["tracked"][:30]  # the old columns first, in place
    posed = [r for r in rows if r["pose_easting"]]
    registered = [r for r in rows if r["how"] == "registered"]
    assert posed and registered and all(r["cov_x_x"] for r in registered)
    assert all(not r["cov_x_x"] for r in rows if r["how"] != "registered")
    utm = np.array([[float(r["pose_easting"]), float(r["pose_northing"]), float(r["pose_height"])]
                    for r in posed])  # fmt: skip
    stamps = [int(r["timestamp"]) * 1000 for r in posed]
    # The MCAP, read back from the file.
    track = read_track(f"{out}.mcap")
    assert list(track.pose_ns) == stamps
    assert np.abs(track.pose_enu - utm).max() < 1e-5  # the CSV's 6 decimals
    assert [s for _, s in track.states] == [r["state"] for r in rows]
    png = plot_mcap(f"{out}.mcap", tmp_path / "from_mcap.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The ROS 2 bag: the poses and the covariance of each registered scan.
    origin = np.array([*track.origin, 0.0])
    with AnyReader([Path(f"{out}_ros2")]) as reader:
        conns = [c for c in reader.connections if c.topic == "/pnvlad/pose"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert len(msgs) == len(posed) and counts["/pnvlad/fix"] == len(posed)
    for m, r in zip(msgs, posed, strict=True):
        p = m.pose.pose.position
        assert np.abs(np.array([p.x, p.y, p.z]) + origin - utm[posed.index(r)]).max() < 1e-5
        if r["how"] == "registered":
            cov = from_upper_triangle([float(r[c]) for c in COVARIANCE_COLUMNS])
            assert np.allclose(np.asarray(m.pose.covariance).reshape(6, 6), cov, rtol=1e-8)
            sigma = math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2])))
            assert sigma == pytest.approx(float(r["sigma_m"]), rel=1e-4)  # the same registration
    # TUM and KITTI, read by evo.
    tum = evo.read_tum_trajectory_file(f"{out}.tum")
    assert np.allclose(tum.timestamps, np.array(stamps) / 1e9, rtol=0, atol=1e-6)
    assert np.abs(tum.positions_xyz + origin - utm).max() < 1e-5
    truth = evo.read_tum_trajectory_file(f"{out}.truth.tum")
    assert truth.num_poses == SCANS
    kitti = evo.read_kitti_poses_file(f"{out}.kitti")
    assert np.abs(kitti.positions_xyz + origin - utm).max() < 1e-5  # every posed scan has truth
    yaw = [math.radians(float(r["pose_yaw_deg"])) for r in posed]
    for se3, y in zip(tum.poses_se3, yaw, strict=True):
        assert math.atan2(se3[1, 0], se3[0, 0]) == pytest.approx(y, abs=1e-5)


def test_a_port_in_use_an_unwritable_mcap_a_bad_zone(
    drive: dict, tiny_maps: dict, tmp_path: Path
) -> None:
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cases = {
            "port": (["--foxglove", f"127.0.0.1:{port}"], "Address already in use"),
            "mcap": (["--mcap", str(blocked / "drive.mcap")], "a_file"),
            "zone": (["--utm-zone", "32Y", "--trajectories", str(tmp_path / "zone")],
                     "utm_zone: '32Y': 'Y' is neither a latitude band"),
        }  # fmt: skip
        for name, (extra, message) in cases.items():
            out = tmp_path / name
            res = CliRunner().invoke(app, [*follow_args(drive, tiny_maps, out), "--no-plot",
                                           *extra])  # fmt: skip
            errors = [ln for ln in res.output.splitlines() if ln.startswith("error: ")]
            assert res.exit_code == 2 and len(errors) == 1, (name, res.output)
            assert message in errors[0], (name, errors)
            rows = read_csv(Path(f"{out}.csv"))  # the drive went on: the CSV complete
            assert [int(r["scan"]) for r in rows] == list(range(SCANS))
            assert "follow: 30 scans" in res.stdout
    assert not list(tmp_path.glob(".*"))  # no partial file left
    assert Path(f"{tmp_path / 'zone'}.tum").is_file()  # the other outputs written


def test_serve_streams_each_answered_query(tiny_maps: dict) -> None:
    """`pnvlad serve --foxglove`: a client subscribed to the server's view receives each
    answer's candidates, its verified pose and its JSON; a port in use is refused at start."""
    from pnvlad_service.client import LocalizeClient
    from pnvlad_service.localization.verify.prior import Prior
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    sim = simulated_drive(get_preset("tiny"), 0, 0, 3)
    port, view_port = free_port(), free_port()
    env = {"PNVLAD_RERANK": "100", "PNVLAD_VERIFY_THRESHOLD": "0.04", "PNVLAD_PRIOR_MAX_SIGMA": "0",
           "PNVLAD_FOXGLOVE": f"127.0.0.1:{view_port}"}  # fmt: skip
    proc = start_server(tiny_maps["keys"], port, env)
    try:
        watcher = Watcher(view_port)
        watcher.start()
        deadline = time.monotonic() + 30
        while "/pnvlad/query/pose" not in watcher.advertised.values():
            assert time.monotonic() < deadline, watcher.advertised
            time.sleep(0.05)
        time.sleep(0.3)  # the subscription sent
        with LocalizeClient(f"http://127.0.0.1:{port}") as client:
            doc = client.localize(sim.scan(5), 5, kind="scan",
                                  prior=Prior.of_matrix(sim.true_poses[5]))  # fmt: skip
            client.localize(sim.scan(9), 5, kind="scan")
        deadline = time.monotonic() + 10
        while watcher.received.get("/pnvlad/query/answer", 0) < 2:
            assert time.monotonic() < deadline, watcher.received
            time.sleep(0.05)
    finally:
        stop_server(proc)
    watcher.join(10)
    assert watcher.error is None, watcher.error
    assert doc["verified"] and doc["pose"] is not None
    assert watcher.received["/pnvlad/query/candidates"] == 2
    assert watcher.received["/pnvlad/query/pose"] >= 1
    assert watcher.received["/pnvlad/map/entries"] >= 1  # sent again to a late subscriber
    assert watcher.schemas["/pnvlad/query/candidates"] == "foxglove.PointCloud"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        used = taken.getsockname()[1]
        cmd = [sys.executable, "-m", "pnvlad_cli.main", "serve", "--index",
               str(tiny_maps["keys"]), "--foxglove", f"127.0.0.1:{used}"]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    errors = [ln for ln in done.stderr.splitlines() if ln.startswith("error: ")]
    assert done.returncode == 2 and len(errors) == 1, done.stderr
    assert errors[0].startswith(f"error: --foxglove: 127.0.0.1:{used}: "), errors
