"""A drive read back from the MCAP its live view wrote (``--mcap``), with the ``mcap`` reader
and the protobuf schemas the file carries, not from the run's memory: the poses, the truth,
the states and the map's entries, in UTM again (the file's ``utm`` -> ``map`` transform); and
drawn as a PNG (:func:`plot_mcap`), the same track the follow's PNG shows.

Example::

    from pnvlad_service.localization.outputs.mcap_track import plot_mcap, read_track

    track = read_track("follow/drive.mcap")
    plot_mcap("follow/drive.mcap", "follow/drive.mcap.png")

or from the shell: ``python -m pnvlad_service.localization.outputs.mcap_track DRIVE.mcap
OUT.png``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.extras import pyplot, require

#: The topics read back.
TOPICS = ("/tf", "/pnvlad/pose", "/pnvlad/truth", "/pnvlad/state", "/pnvlad/map/entries")
#: Colours of how a pose came, as the follow's PNG draws them.
HOW_COLOURS = {"registered": ("tab:green", "tracking, verified"), "fix": ("tab:blue", "fix"),
               "predicted": ("tab:orange", "predicted (not verified)")}  # fmt: skip


@dataclass(frozen=True)
class McapTrack:
    """What an MCAP says of a drive: ``pose_ns`` int64 [P] and ``pose_enu`` float64 [P, 3]
    (UTM east, north, up) of each pose; ``truth_ns`` / ``truth_enu`` the same of the truth;
    ``states``: (ns, state) of each scan, ``hows``: (ns, how its pose came); ``entries``
    float64 [M, 3] (UTM) of the map's entries (empty when not in the file); ``origin``: the
    ``map`` frame's (east, north)."""

    pose_ns: np.ndarray
    pose_enu: np.ndarray
    truth_ns: np.ndarray
    truth_enu: np.ndarray
    states: tuple[tuple[int, str], ...]
    hows: tuple[tuple[int, str], ...]
    entries: np.ndarray
    origin: tuple[float, float]


class _Decoders:
    """Protobuf message classes built from the schemas in the file (FileDescriptorSets)."""

    def __init__(self) -> None:
        require("google.protobuf", "protobuf", "view", "reading an MCAP back")
        from google.protobuf import descriptor_pool

        self.pool = descriptor_pool.DescriptorPool()
        self.classes: dict[int, Any] = {}

    def decode(self, schema: Any, data: bytes) -> Any:
        if schema.encoding == "jsonschema":
            return json.loads(data)
        cls = self.classes.get(schema.id)
        if cls is None:
            from google.protobuf import descriptor_pb2, message_factory

            fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            for f in fds.file:
                try:
                    self.pool.FindFileByName(f.name)
                except KeyError:
                    self.pool.Add(f)
            cls = message_factory.GetMessageClass(self.pool.FindMessageTypeByName(schema.name))
            self.classes[schema.id] = cls
        return cls.FromString(data)


class _Collect:
    """What the messages say, topic by topic."""

    def __init__(self) -> None:
        self.origin: tuple[float, float] | None = None
        self.poses: list[tuple[int, list[float]]] = []
        self.truths: list[tuple[int, list[float]]] = []
        self.states: list[tuple[int, str]] = []
        self.hows: list[tuple[int, str]] = []
        self.entries = np.zeros((0, 3))

    def take(self, topic: str, ns: int, msg: Any) -> None:
        if topic == "/tf":
            for t in msg.transforms:
                if t.parent_frame_id == "utm" and t.child_frame_id == "map":
                    self.origin = (t.translation.x, t.translation.y)
        elif topic in ("/pnvlad/pose", "/pnvlad/truth"):
            p = msg.pose.position
            (self.poses if topic == "/pnvlad/pose" else self.truths).append((ns, [p.x, p.y, p.z]))
        elif topic == "/pnvlad/state":
            self.states.append((ns, str(msg.get("state"))))
            self.hows.append((ns, str(msg.get("how"))))
        elif topic == "/pnvlad/map/entries":
            self.entries = np.frombuffer(msg.data, dtype="<f4").reshape(-1, 3).astype(np.float64)


def read_track(path: str | Path) -> McapTrack:
    """The drive in the MCAP at ``path``; InputError naming it when it is not an MCAP, or not
    a drive's (no ``utm`` -> ``map`` transform)."""
    reader_mod = require("mcap.reader", "mcap", "view", "reading an MCAP back")
    from mcap.exceptions import McapError

    path = Path(path)
    dec, got = _Decoders(), _Collect()
    try:
        with open(path, "rb") as fh:
            reader = reader_mod.make_reader(fh)
            for schema, channel, message in reader.iter_messages(topics=list(TOPICS)):
                got.take(channel.topic, int(message.log_time), dec.decode(schema, message.data))
    except McapError as exc:
        raise InputError(f"not a readable MCAP file ({exc})", path) from None
    if got.origin is None:
        raise InputError("not a drive's MCAP: no utm -> map transform on /tf", path)
    shift = np.array([got.origin[0], got.origin[1], 0.0])

    def arrays(items: list[tuple[int, list[float]]]) -> tuple[np.ndarray, np.ndarray]:
        ns = np.array([t for t, _ in items], dtype=np.int64)
        xyz = np.array([v for _, v in items], dtype=np.float64).reshape(-1, 3) + shift
        return ns, xyz

    pose_ns, pose_enu = arrays(got.poses)
    truth_ns, truth_enu = arrays(got.truths)
    entries = got.entries + shift if len(got.entries) else got.entries
    return McapTrack(pose_ns, pose_enu, truth_ns, truth_enu, tuple(got.states), tuple(got.hows),
                     entries, got.origin)  # fmt: skip


def plot_mcap(path: str | Path, out: str | Path, title: str | None = None) -> Path:
    """A PNG of the drive in the MCAP at ``path`` (:func:`read_track`): the map's entries, the
    truth and the poses coloured by how each came (a fix, a registration, the odometry's
    prediction), UTM metres; written to ``out``."""
    track = read_track(path)
    plt = pyplot("the MCAP's PNG")
    how_at = dict(track.hows)
    fig, ax = plt.subplots(figsize=(8, 8))
    try:
        if len(track.entries):
            ax.scatter(track.entries[:, 0], track.entries[:, 1], s=6, c="0.7", label="map entries")
        if len(track.truth_enu):
            ax.plot(track.truth_enu[:, 0], track.truth_enu[:, 1], "k-", lw=1, label="truth")
        hows = np.array([how_at.get(int(t), "") for t in track.pose_ns])
        for how, (colour, label) in HOW_COLOURS.items():
            sel = hows == how
            if sel.any():
                ax.scatter(track.pose_enu[sel, 0], track.pose_enu[sel, 1], s=12, c=colour,
                           zorder=3, label=f"{label} ({int(sel.sum())})")  # fmt: skip
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.set_xlabel("easting (m, UTM)")
        ax.set_ylabel("northing (m, UTM)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(title or f"{Path(path).name}: the drive as its MCAP has it")
        ax.legend(loc="best", fontsize=8)
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.partial.png")
        fig.savefig(tmp, dpi=110)
        tmp.replace(out)
    finally:
        plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m pnvlad_service.localization.outputs.mcap_track DRIVE.mcap OUT.png``."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(
        prog="python -m pnvlad_service.localization.outputs.mcap_track",
        description="Draw the drive in an MCAP written by `pnvlad localize --mcap` as a PNG: "
        "the map's entries, the truth, the poses coloured by how each came.",
    )
    parser.add_argument("mcap", type=Path, help="the MCAP file (pnvlad localize --mcap)")
    parser.add_argument("png", type=Path, help="the PNG to write")
    args = parser.parse_args(argv)
    try:
        print(f"wrote {plot_mcap(args.mcap, args.png)}")
    except (InputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
