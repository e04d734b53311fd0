"""`pnvlad data preprocess`: one raw scan through the filter G into one submap file."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from pnvlad_cli.common import user_errors

if TYPE_CHECKING:
    from pnvlad_service.preprocess.filter_g import GConfig

_READER_NAMES = "benchmark, kitti, nuscenes, nclt, npy, pcd, ply, las"
_OPTION_OF = {
    "target_points": "--points",
    "ground_mode": "--ground-mode",
    "ground_threshold": "--ground-threshold",
    "up": "--up",
    "min_range": "--min-range",
    "max_range": "--max-range",
    "box": "--box",
}


def _parse_box(text: str | None) -> tuple[float, ...] | None:
    from pnvlad_service.errors import InputError

    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 6:
        raise InputError(
            f"expected six comma-separated numbers xmin,ymin,zmin,xmax,ymax,zmax, got {text!r}",
            source="--box",
        )
    return values


def _g_config(fields: dict[str, Any], **flags: bool) -> GConfig:
    """``GConfig`` of the options given; a refused value is reported under its option name."""
    from pydantic import ValidationError

    from pnvlad_service.errors import InputError
    from pnvlad_service.preprocess.filter_g import GConfig

    try:
        return GConfig(**fields, **flags)
    except ValidationError as exc:
        err = exc.errors()[0]
        name = str(err["loc"][0]) if err["loc"] else ""
        raise InputError(err["msg"], source=_OPTION_OF.get(name, "options")) from None


def preprocess(
    scan: Path = typer.Argument(
        ..., exists=True, dir_okay=False, readable=True, help="The point cloud to preprocess."
    ),
    out: Path = typer.Option(
        ..., "--out", "-o", help="Output submap: .bin (float64 x, y, z, no header) or .npy."
    ),
    reader: str | None = typer.Option(
        None,
        "--reader",
        help=f"Input format: {_READER_NAMES}. Default: by suffix; a raw .bin needs it "
        "(except a 98,304-byte benchmark submap).",
    ),
    points: int | None = typer.Option(
        None, "--points", help="Points in the submap. Default: 4096."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the random refill/drop steps."),
    no_normalize: bool = typer.Option(
        False,
        "--no-normalize",
        help="Keep the input frame and metres (skip centring, scaling to mean distance 0.5 and "
        "clipping to [-1, 1]).",
    ),
    negate: bool = typer.Option(
        False, "--negate", help="Negate the coordinates, as the published MATLAB script did."
    ),
    no_ground: bool = typer.Option(False, "--no-ground-removal", help="Keep the ground."),
    ground_mode: str | None = typer.Option(
        None,
        "--ground-mode",
        help="'local' (height above a grid surface that follows slopes and kerbs) or 'plane' "
        "(one RANSAC plane, the paper). Default: local.",
    ),
    ground_threshold: float | None = typer.Option(
        None,
        "--ground-threshold",
        help="Points less than this many metres above the ground are removed. [default: 0.5]",
    ),
    up: str | None = typer.Option(
        None,
        "--up",
        help="Up side of the ground: auto, z or -z (NCLT's frame is z-down; auto finds it). "
        "Default: auto.",
    ),
    min_range: float | None = typer.Option(
        None, "--min-range", help="Drop points closer than this to the sensor (m)."
    ),
    max_range: float | None = typer.Option(
        None, "--max-range", help="Drop points farther than this from the sensor (m)."
    ),
    box: str | None = typer.Option(
        None, "--box", help="Keep only points in xmin,ymin,zmin,xmax,ymax,zmax (m)."
    ),
) -> None:
    """Run one scan through the filter G and write one benchmark submap.

    G crops (off unless asked), removes the ground, voxel-averages to --points points and
    normalises them: centred, mean distance 0.5, inside [-1, 1]. The submap is .bin (float64
    x, y, z, no header: 98,304 bytes for 4096 points) or .npy, by the suffix of --out. Prints
    one line: points read, after the crop, after ground removal, and written.

    Example:

        pnvlad data preprocess kitti/velodyne/000000.bin --reader kitti --out 000000.bin
    """
    with user_errors():
        from pnvlad_service.errors import InputError
        from pnvlad_service.io.readers import read_points
        from pnvlad_service.io.submap import write_submap
        from pnvlad_service.preprocess.filter_g import apply_g

        if out.suffix.lower() not in (".bin", ".npy"):
            raise InputError("the submap is written as .bin or .npy", source=out)
        options = {
            "target_points": points,
            "ground_mode": ground_mode,
            "ground_threshold": ground_threshold,
            "up": up,
            "min_range": min_range,
            "max_range": max_range,
            "box": _parse_box(box),
        }
        fields = {k: v for k, v in options.items() if v is not None}
        config = _g_config(
            fields, normalize=not no_normalize, negate=negate, remove_ground=not no_ground
        )
        cloud = read_points(scan, reader)
        result = apply_g(cloud, config, seed=seed)
        write_submap(out, result.points)
        typer.echo(
            f"{scan.name}: {result.n_input:,} points in, {result.n_cropped:,} after crop, "
            f"{result.n_nonground:,} after ground removal, {result.points.shape[0]:,} out "
            f"(leaf {result.leaf_size:.3f} m) -> {out}"
        )


def register(app: typer.Typer) -> None:
    """Add this module's commands to the `pnvlad data` group."""
    app.command("preprocess")(preprocess)
