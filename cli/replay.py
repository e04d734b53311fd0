"""`pnvlad localize --rosbag`: replay a bag's scans against the service, a CSV and a PNG out.

Called by `pnvlad localize` (cli/serve.py) when ``--rosbag`` is given: every Nth scan of the
bag's cloud topic goes as a raw-scan query (``preprocess: true``) to a server (``--url``) or to a
bundle searched in this process (``--index``); :mod:`pnvlad_service.localization.replay` makes
the rows, the CSV, the PNG and the summary line. Library imports happen inside the functions so
that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli import rosbag as bag_options

PANEL = "Replay (with --rosbag)"

ORIGIN = typer.Option(
    None,
    "--origin",
    help="With --rosbag and poses: UTM NORTHING,EASTING of the pose frame's origin (default 0,0).",
    rich_help_panel=PANEL,
)
YAW = typer.Option(
    0.0,
    "--yaw",
    help="With --rosbag and poses: direction of the pose frame's x axis, degrees "
    "counter-clockwise from east.",
    rich_help_panel=PANEL,
)
EVERY = typer.Option(
    None, "--every", help="With --rosbag: send every Nth scan (default 10).", rich_help_panel=PANEL
)
OUT = typer.Option(
    None,
    "--out",
    "-o",
    help="With --rosbag: write OUT.csv (one row a query) and OUT.png (default: the bag's "
    "name beside it, e.g. drive.replay.csv).",
    rich_help_panel=PANEL,
)
MAP = typer.Option(
    None,
    "--map",
    help="With --rosbag --url: a copy of the server's bundle, to draw the map's submaps in "
    "the PNG (with --index the bundle is used).",
    rich_help_panel=PANEL,
)
PLOT = typer.Option(
    True,
    "--plot/--no-plot",
    help="With --rosbag: write the PNG (needs the 'plot' extra).",
    rich_help_panel=PANEL,
)


def parse_origin(text: str | None) -> tuple[float, float]:
    """``--origin`` NORTHING,EASTING -> (northing, easting); (0, 0) when not given."""
    if text is None:
        return (0.0, 0.0)
    from pnvlad_cli.data_prepare import _parse_origin

    return _parse_origin(text)


@contextmanager
def _service(
    url: str | None, index: Path | None, model: Path | None, api_key: str | None, top_n: int
) -> Iterator[Callable[[Any], dict[str, Any]]]:
    """``ask(points) -> answer`` for raw scans, from a server or from a local bundle."""
    if url is not None:
        from pnvlad_service.localization.client import LocalizeClient

        with LocalizeClient(url, api_key=api_key) as client:
            yield lambda points: client.localize(points, top_n, preprocess=True)
        return
    from pnvlad_service.localization.limits import Limits
    from pnvlad_service.localization.localizer import Localizer

    assert index is not None
    with Localizer.load(index, model) as loc:

        def ask(points: Any) -> dict[str, Any]:
            # A local query is bounded by the bundle, not by the server's request limits.
            limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
            return loc.localize(points, preprocess=True, top_n=top_n, limits=limits).to_json()

        yield ask


def _map_positions(bundle: Path | None) -> Any:
    """float [M, 2] (northing, easting) of a bundle's submaps, or None."""
    if bundle is None:
        return None
    import numpy as np

    from pnvlad_service.index.bundle import METADATA_FILE, Metadata

    meta = Metadata.load(Path(bundle) / METADATA_FILE)
    return np.c_[meta.northing, meta.easting]


def replay_rosbag(
    *,
    rosbag: Path,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    origin_ne: tuple[float, float],
    yaw_deg: float,
    max_pose_gap: float | None,
    url: str | None,
    index: Path | None,
    model: Path | None,
    api_key: str | None,
    every: int | None,
    out: Path | None,
    map_bundle: Path | None,
    plot: bool,
    top_n: int = 5,
    progress: bool = True,
) -> None:
    """The whole replay: open the bag, ask, write OUT.csv and OUT.png, print the summary."""
    from pnvlad_service.data.sources.rosbag import RosbagClouds
    from pnvlad_service.errors import InputError
    from pnvlad_service.localization.replay import (
        plot_replay,
        replay,
        summarise,
        write_replay_csv,
    )

    every = 10 if every is None else every
    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "--every")
    if pose_topic is None and tf_frame is None:
        if cloud_topic is None:
            raise InputError("--rosbag needs --cloud-topic (see `pnvlad data prepare "
                             "--rosbag BAG --list`)", "--cloud-topic")  # fmt: skip
        drive: Any = RosbagClouds(rosbag, cloud_topic)
    else:
        drive = bag_options.open_drive(
            rosbag, cloud_topic, pose_topic, tf_frame, origin_ne=origin_ne, yaw_deg=yaw_deg,
            max_pose_gap=max_pose_gap,
        )  # fmt: skip
    if out is None:
        out = rosbag.with_name(f"{drive.name}.replay")
    try:
        map_ne = _map_positions(index if index is not None else map_bundle)
        with _service(url, index, model, api_key, top_n) as ask:
            rows = replay(drive, ask, every=every, progress=progress)
    finally:
        drive.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    csv_path = write_replay_csv(rows, out.with_name(out.name + ".csv"))
    written = [str(csv_path)]
    if plot:
        poses = getattr(drive, "poses", None)
        png = plot_replay(
            rows,
            out.with_name(out.name + ".png"),
            map_ne=map_ne,
            trajectory_ne=None if poses is None else poses[:, [1, 0], 3],
            title=f"{drive.name}: {cloud_topic}, one scan in {every}",
        )
        written.append(str(png))
    typer.echo(f"wrote {', '.join(written)}")
    typer.echo(summarise(rows).line())
