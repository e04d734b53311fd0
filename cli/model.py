"""`pnvlad model`: import weights from the PyTorch port, inspect a model directory, export it to
ONNX."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from pnvlad_cli.common import user_errors

app = typer.Typer(
    rich_markup_mode="markdown",
    help=(
        "Model directories (model.json + model.safetensors): import weights trained with the "
        "PyTorch port of PointNetVLAD, show what a model directory holds, or export its encoder "
        "to ONNX (model.onnx) for a server without torch."
    ),
    no_args_is_help=True,
)


@app.command("import")
def import_(
    port_ckpt: Path = typer.Argument(
        ...,
        help="Checkpoint of cattaneod/PointNetVlad-Pytorch (torch.save of {'state_dict': ...}, "
        "a bare state dict, or a DataParallel one with 'module.' names).",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Model directory to create."),
    feature_transform: bool = typer.Option(
        True,
        "--feature-transform/--no-feature-transform",
        help="Whether the port model was built with feature_transform=True (its default "
        "training script does). The port saves the feature transform's weights either way, "
        "so this cannot be read from the file.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace --out if it exists."),
) -> None:
    """Convert a PointNetVlad-Pytorch checkpoint into a pnvlad model directory.

    The file is read with torch.load(weights_only=True): plain tensors and containers only;
    anything else is refused. Every tensor is mapped to its place in our model; a file that does
    not fit (missing, unexpected or mis-shaped tensors) is refused with the full list. The
    result runs under the 'port' configuration (batch norm in the trunk, none in the transform
    nets, no ReLU after the last layer) and its descriptors equal the port's, L2-normalised.

    Example: pnvlad model import runs/pointnetvlad/checkpoint.pth.tar --out models/port
    """
    with user_errors():
        from pnvlad_service.models.port import import_port
        from pnvlad_service.models.store import weights_sha256

        out_dir, cfg = import_port(
            port_ckpt, out, feature_transform=feature_transform, overwrite=overwrite
        )
        typer.echo(
            f"imported {port_ckpt} -> {out_dir} ({cfg.arch}, K={cfg.cluster_size}, "
            f"output {cfg.output_dim}, weights sha256 {weights_sha256(out_dir)[:16]})"
        )


@app.command("info")
def info(
    model_dir: Path = typer.Argument(
        ...,
        help="Model directory (model.json + model.safetensors) or a training run directory "
        "(its model/ is used).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of text."),
) -> None:
    """Show a model directory's configuration, parameter count, FLOPs and checksums.

    Checks the weights against the SHA-256 recorded in model.json and loads them into the model
    (exit 2 if either fails).

    Example: pnvlad model info models/port --json
    """
    with user_errors():
        from pnvlad_service.models.store import (
            config_sha256,
            load_model,
            resolve_model_dir,
            weights_sha256,
        )

        model_dir = resolve_model_dir(model_dir)
        model, cfg = load_model(model_dir)
        doc = {
            "dir": str(model_dir),
            "model": cfg.model_dump(mode="json"),
            "parameters": sum(p.numel() for p in model.parameters()),
            "gflop_per_cloud": round(cfg.flops_per_cloud() / 1e9, 3),
            "weights_sha256": weights_sha256(model_dir),
            "config_sha256": config_sha256(cfg),
        }
        if as_json:
            typer.echo(json.dumps(doc, indent=2))
            return
        typer.echo(
            f"{model_dir}: {cfg.arch}, {doc['parameters']:,} parameters, "
            f"{doc['gflop_per_cloud']} GFLOP per {cfg.num_points}-point cloud"
        )
        for k, v in doc["model"].items():
            typer.echo(f"  {k:18s} {v}")
        typer.echo(f"  weights_sha256     {doc['weights_sha256']}")
        typer.echo(f"  config_sha256      {doc['config_sha256']}")


@app.command("export")
def export(
    model_dir: Path = typer.Argument(
        ...,
        help="Model directory (model.json + model.safetensors) or a training run directory "
        "(its model/ is used). model.onnx is written into it.",
    ),
    point_tile: int = typer.Option(
        512,
        "--point-tile",
        help="Points a tile of the widest per-point layers in the graph (0: whole clouds).",
    ),
    check_tree: Path = typer.Option(
        None,
        "--check-root",
        help="A benchmark tree whose test-layout submaps are checked too (real clouds; "
        "default: the seeded check clouds only).",
    ),
    check_count: int = typer.Option(
        64, "--check-count", help="With --check-root: submaps checked (the first ones)."
    ),
) -> None:
    """Write the encoder as model.onnx beside its weights, for a server without torch.

    The graph is the fast inference path (batch norms folded; PN_VLAD, PN_MAX and bev-netvlad,
    with canonical heading when the model has it), with a dynamic batch size. Before it is
    written, ONNX Runtime's descriptors of the check clouds (seeded street-like clouds, and
    --check-root's submaps) must be within cosine 0.9999 of torch's, as one batch and one cloud
    at a time; exit 2 otherwise. The file records the sha256 of the weights and configuration
    it came from: `pnvlad serve` refuses it beside other weights. Needs torch and onnx
    (pip install 'pnvlad[torch]').

    Example: pnvlad model export runs/model
    """
    with user_errors():
        import numpy as np

        from pnvlad_service.models.onnx_export import export_onnx

        points = None
        if check_tree is not None:
            from pnvlad_service.index.build import list_database_submaps
            from pnvlad_service.io.readers import read_points

            records = list_database_submaps(check_tree)[:check_count]
            points = np.stack([read_points(check_tree / r.path, "benchmark") for r in records])
        report = export_onnx(model_dir, point_tile=point_tile, points=points)
        typer.echo(
            f"wrote {report.path} ({report.bytes / 1e6:.1f} MB): {report.clouds} clouds within "
            f"cosine {report.min_cosine:.6f} of torch (>= 0.9999), {report.seconds:.1f} s"
        )
