"""`pnvlad model`: import weights from the PyTorch port, inspect a model directory, export it to
ONNX, list the pretrained models that ship with pnvlad and add one to their catalogue."""

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
        "to ONNX (model.onnx) for a server without torch. Pretrained models ship with pnvlad: "
        "`pnvlad model list` shows them; any command that takes a model takes "
        "pretrained:NAME."
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
        help="Model directory (model.json + model.safetensors), a training run directory "
        "(its model/ is used) or pretrained:NAME (pnvlad model list).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of text."),
) -> None:
    """Show a model directory's configuration, parameter count, FLOPs and checksums.

    Checks the weights against the SHA-256 recorded in model.json and loads them into the model
    (exit 2 if either fails).

    Example: pnvlad model info models/port --json; pnvlad model info pretrained:bev-benchmark
    """
    with user_errors():
        from pnvlad_service.models.store import (
            config_sha256,
            load_model,
            resolve_model_dir,
            weights_sha256,
        )

        ref = _pretrained_ref(model_dir)
        model_dir = resolve_model_dir(ref)
        model, cfg = load_model(model_dir)
        doc = {
            "dir": str(model_dir),
            **({"pretrained": _entry_json(ref)} if isinstance(ref, str) else {}),
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
        for k, v in doc.get("pretrained", {}).items():
            if k not in ("files", "name", "dir"):
                typer.echo(f"  {k:18s} {json.dumps(v) if isinstance(v, dict) else v}")


def _pretrained_ref(model_dir: Path) -> Path | str:
    """``model_dir`` (a Path), or the string ``pretrained:NAME`` when it is one or is a bare
    name the catalogue lists and no such path exists (`pnvlad model info bev-benchmark`)."""
    from pnvlad_service.errors import PnvladError
    from pnvlad_service.models.pretrained import PREFIX, Catalogue, is_pretrained

    if is_pretrained(model_dir) or model_dir.exists():
        return str(model_dir) if is_pretrained(model_dir) else model_dir
    try:
        names = Catalogue.read().names
    except PnvladError:
        return model_dir
    return f"{PREFIX}{model_dir}" if str(model_dir) in names else model_dir


def _entry_json(ref: str | Path) -> dict:
    """The catalogue entry of ``pretrained:NAME`` as JSON."""
    from pnvlad_service.models.pretrained import PREFIX, Catalogue

    return Catalogue.read().get(str(ref)[len(PREFIX) :]).to_json()


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


@app.command("list")
def list_(
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of text."),
) -> None:
    """List the pretrained models that ship with pnvlad, and check their files.

    One line a model: name, kind (submap or scan queries), encoder, stored dtype, size, its
    figures, and whether every file matches the SHA-256 the catalogue records (OK, or what is
    wrong: exit 2 when any file is missing or corrupt). Select one anywhere a model is taken
    with pretrained:NAME. PNVLAD_PRETRAINED names another catalogue file.

    Example: pnvlad model list; pnvlad index build -m pretrained:bev-benchmark -r city -o map
    """
    with user_errors():
        from pnvlad_service.models.pretrained import Catalogue

        cat = Catalogue.read()
        rows = []
        for e in cat.entries:
            problems = cat.problems(e)
            rows.append((e, problems))
        if as_json:
            doc = {
                "catalogue": str(cat.path),
                "bytes": cat.bytes,
                "models": [
                    {**e.to_json(), "bytes": e.bytes, "verified": not p, "problems": p}
                    for e, p in rows
                ],
            }
            typer.echo(json.dumps(doc, indent=2))
        else:
            _print_catalogue(cat, rows)
        bad = [p for _, p in rows if p]
        if bad:
            typer.secho(f"error: {bad[0][0]}", err=True, fg=typer.colors.RED)
            raise typer.Exit(code=2)


def _print_catalogue(cat, rows: list) -> None:
    """The text of `pnvlad model list`."""
    if not rows:
        typer.echo(f"no pretrained models in {cat.path}")
        return
    typer.echo(f"{len(rows)} pretrained models, {cat.bytes / 2**20:.1f} MiB ({cat.path}):")
    for e, problems in rows:
        figures = ", ".join(f"{k} {v}" for k, v in e.figures.items()) or "no figures recorded"
        state = "OK" if not problems else f"CORRUPT ({len(problems)} files)"
        typer.echo(
            f"  pretrained:{e.name:22s} {e.kind:7s} {e.encoder:13s} {e.dtype:8s} "
            f"{e.bytes / 2**20:6.1f} MiB  sha256 {state}  {figures}"
        )
        for problem in problems:
            typer.echo(f"    {problem}")


@app.command("package")
def package(
    source: Path = typer.Argument(
        ...,
        help="The trained model: a model directory or a training run directory (its model/).",
    ),
    name: str = typer.Option(
        ..., "--name", help="Its pretrained name (lower-case, digits, dashes)."
    ),
    kind: str = typer.Option("submap", "--kind", help="The queries it is for: submap or scan."),
    float16: bool = typer.Option(
        True, "--fp16/--fp32", help="Store the weight matrices as float16 (half the size)."
    ),
    onnx: bool = typer.Option(
        True, "--onnx/--no-onnx", help="Write model.onnx too, for a server without torch."
    ),
    trained_with: str = typer.Option("", "--trained-with", help="The command that trained it."),
    data: str = typer.Option("", "--data", help="Its training data, in words."),
    figure: list[str] = typer.Option(
        [], "--figure", help="KEY=VALUE, e.g. --figure 'recall@1 (benchmark)=97.1'; repeat."
    ),
    check_tree: Path = typer.Option(
        None, "--check-root", help="A benchmark tree whose submaps join the stored-dtype check."
    ),
    check_count: int = typer.Option(
        256, "--check-count", help="With --check-root: submaps checked (the first ones)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a model of this name."),
    embed_scales: str = typer.Option(
        None,
        "--embed-scales",
        help="Scales to embed each cloud at, descriptors averaged (e.g. 0.85,1,1.18; the "
        "model's embed_scales; '' for none). Default: as the model was trained.",
    ),
) -> None:
    """Add a trained model to the pretrained catalogue (pnvlad_service/pretrained/).

    Copies the model under --name with its weight matrices as float16 (--fp16, the default;
    torch and ONNX Runtime compute in float32 from them) and its model.onnx, checks that the
    stored model's descriptors stay within cosine 0.999 of the original's on 64 seeded
    street-like clouds (and --check-root's submaps), holds it to the size limits (48 MiB a
    model, 64 MiB all together), then writes the directory and the catalogue's entry (files'
    SHA-256 and sizes, the command, data, figures, today's date) atomically: on any error
    nothing is written. PNVLAD_PRETRAINED names another catalogue file. Needs torch and onnx.

    Example: pnvlad model package runs/bev --name bev-benchmark --trained-with "pnvlad train -c
    bev --root bench --splits bench/splits.json -o runs/bev" --data "benchmark preset, seed 1"
    --figure "recall@1 (benchmark)=97.1"
    """
    with user_errors():
        from pnvlad_service.errors import InputError
        from pnvlad_service.models.packaging import Card, package_model

        figures = {}
        for item in figure:
            key, sep, value = item.partition("=")
            if not sep or not key.strip():
                raise InputError(f"expected KEY=VALUE, got {item!r}", "--figure")
            figures[key.strip()] = _number(value.strip())
        points = None
        if check_tree is not None:
            points = _check_points(check_tree, check_count)
        card = Card(kind=kind, trained_with=trained_with, data=data, figures=figures)
        entry = package_model(
            source,
            name,
            card,
            float16=float16,
            onnx=onnx,
            points=points,
            overwrite=overwrite,
            embed_scales=_scales(embed_scales),
        )
        fid = entry.extra["fidelity"]
        typer.echo(
            f"packaged {source} as pretrained:{entry.name} ({entry.dtype}, "
            f"{entry.bytes / 2**20:.1f} MiB, {', '.join(entry.files)}): descriptors within "
            f"cosine {fid['min_cosine']:.6f} of the original's on {fid['clouds']} clouds, "
            f"top-1 agreement {fid['top1_agreement']:.3f}"
        )


def _scales(text: str | None) -> tuple[float, ...] | None:
    """``--embed-scales``: comma-separated numbers ('' for none; None: not given)."""
    from pnvlad_service.errors import InputError

    if text is None:
        return None
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError as exc:
        raise InputError(f"expected numbers, got {text!r}", "--embed-scales") from exc


def _number(text: str) -> float | int | str:
    """``text`` as an int or float when it is one."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _check_points(tree: Path, count: int):
    """The first ``count`` database submaps of the benchmark tree ``tree``, float [M, N, 3]."""
    import numpy as np

    from pnvlad_service.index.build import list_database_submaps
    from pnvlad_service.io.readers import read_points

    records = list_database_submaps(tree)[:count]
    return np.stack([read_points(tree / r.path, "benchmark") for r in records])
