"""`pnvlad train`: train the encoder on a benchmark tree (one process, or several with torchrun)."""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli.common import (
    pickles_option,
    progress_option,
    root_option,
    splits_option,
    user_errors,
)

_DATA = "Data"
_RUN = "Run"
_MODEL = "Model and optimiser"

# -c is --config here (and only here): see pnvlad_cli.common.
_CONFIG = typer.Option(
    None,
    "--config",
    "-c",
    help="YAML/TOML config file, or a shipped preset name: 'paper' (default), 'compact', "
    "'cpu' (compact PN_VLAD + in-batch mining, augmentation, cosine schedule), 'bev' (the "
    "best recall on a CPU budget: cpu's training of a bird's-eye-view CNN + NetVLAD, "
    "bev-netvlad; not the paper's network), or 'bev_scan' / 'cpu_scan' (those two for single "
    "scans: trained on the keyframe maps, splits_keyframes.json, each cloud turned to its own "
    "dominant direction).",
    rich_help_panel=_RUN,
)
_OUT = typer.Option(
    None,
    "--out",
    "-o",
    help="Run directory: checkpoints/, metrics.jsonl, config.yaml and the final model/.",
    rich_help_panel=_RUN,
)
_RESUME = typer.Option(
    False,
    "--resume",
    help="Continue the run in --out from its newest checkpoint (its config.yaml unless "
    "--config is given; options given here still apply).",
    rich_help_panel=_RUN,
)
_INIT = typer.Option(
    None,
    "--init",
    help="Start from these weights instead of random ones (fine-tuning on your map): "
    "pretrained:NAME, a training run or model directory, or a .safetensors/.pt weights file. "
    "They must fit the config's model (-c: the one they were trained with); a layer that "
    "does not is named.",
    rich_help_panel=_MODEL,
)
_EPOCHS = typer.Option(None, "--epochs", help="Epochs (paper: 20).", rich_help_panel=_RUN)
_MAX_STEPS = typer.Option(None, "--max-steps", help="Stop after N steps.", rich_help_panel=_RUN)
_MAX_MINUTES = typer.Option(
    None,
    "--max-minutes",
    help="Wall-clock budget; checkpoint and stop when spent.",
    rich_help_panel=_RUN,
)
_BATCH = typer.Option(
    None, "--batch-size", "-b", help="Tuples a step (paper: 2).", rich_help_panel=_MODEL
)
_LR = typer.Option(None, "--lr", help="Base learning rate (paper: 5e-5).", rich_help_panel=_MODEL)
_ARCH = typer.Option(
    None,
    "--arch",
    help="pointnetvlad | pointnet-max | bev-netvlad (its sizes: -c bev, or --set model.bev_*).",
    rich_help_panel=_MODEL,
)
_NUM_POINTS = typer.Option(
    None,
    "--num-points",
    help="Points a cloud (4096; fewer for quick tests).",
    rich_help_panel=_MODEL,
)
_LOSS = typer.Option(
    None,
    "--loss",
    help="lazy_quadruplet (paper) | lazy_triplet | quadruplet | triplet.",
    rich_help_panel=_MODEL,
)
_MINING = typer.Option(
    None,
    "--mining",
    help="tuple (paper: cached hard negatives) | in_batch (reuse every embedding).",
    rich_help_panel=_MODEL,
)
_DEVICE = typer.Option(
    None,
    "--device",
    help="auto (CUDA when present) | cpu | cuda | cuda:N.",
    rich_help_panel=_RUN,
)
_SEED = typer.Option(None, "--seed", help="Seed of every random choice.", rich_help_panel=_RUN)
_WORKERS = typer.Option(
    None,
    "--workers",
    help="Threads reading submaps into RAM (default 4).",
    rich_help_panel=_RUN,
)
_SET = typer.Option(
    None,
    "--set",
    help="FIELD=VALUE: any config field, dotted as in --dump-config, the value read as YAML "
    "(repeatable; after the file, before the options above): --set model.output_dim=128 "
    "--set train.augment.yaw_deg=0 --set 'model.trunk_widths=[64, 128, 512]'.",
    rich_help_panel=_MODEL,
)
_DUMP = typer.Option(
    False,
    "--dump-config",
    help="Print the resolved config (defaults, file, options) as YAML and exit.",
    rich_help_panel=_RUN,
)


def train(
    config: str = _CONFIG,
    root: Path = root_option(panel=_DATA),
    splits: Path = splits_option(panel=_DATA),
    pickles: Path = pickles_option("Folder of the published pickles instead of --splits.", _DATA),
    out: Path = _OUT,
    resume: bool = _RESUME,
    init: str = _INIT,
    epochs: int = _EPOCHS,
    max_steps: int = _MAX_STEPS,
    max_minutes: float = _MAX_MINUTES,
    batch_size: int = _BATCH,
    lr: float = _LR,
    arch: str = _ARCH,
    num_points: int = _NUM_POINTS,
    loss: str = _LOSS,
    mining: str = _MINING,
    device: str = _DEVICE,
    seed: int = _SEED,
    workers: int = _WORKERS,
    assignments: list[str] = _SET,
    dump_config: bool = _DUMP,
    progress: bool = progress_option(),
) -> None:
    """Train PointNetVLAD on a benchmark tree and its splits.

    Each step takes tuples of 1 anchor, 2 positives, 18 negatives (hard ones from a descriptor
    cache refreshed on schedule) and 1 other negative, embeds every distinct cloud once and
    applies the lazy quadruplet loss; Adam with the paper's learning rate and decay. Writes
    OUT/checkpoints/ (resumable with --resume), OUT/metrics.jsonl (loss, learning rate, cache
    refreshes, validation recall) and the final weights in OUT/model/ for 'pnvlad eval'. Several
    processes or machines: torchrun --nproc-per-node 2 -m pnvlad_cli.main train ...

    Examples:

      pnvlad train --dump-config > my.yaml

      pnvlad train -c compact --root city/ --splits city/splits.json -o runs/a --max-minutes 10

      pnvlad train -c compact -o runs/a --resume

      pnvlad train -c compact --set model.output_dim=128 --dump-config
    """
    with user_errors():
        from pnvlad_service.errors import InputError
        from pnvlad_service.training.config import parse_assignments, run_config

        if resume and out is None:
            raise InputError("--resume needs --out, the run directory to continue", "--out")
        cfg = run_config(config, out if resume else None)
        cfg = cfg.with_overrides(parse_assignments(assignments or [])).with_overrides(
            {
                "data.root": root,
                "data.splits": splits,
                "data.pickles": pickles,
                "train.epochs": epochs,
                "train.max_steps": max_steps,
                "train.max_minutes": max_minutes,
                "train.init": init,
                "train.batch_size": batch_size,
                "train.lr": lr,
                "train.loss": loss,
                "train.mining": mining,
                "train.device": device,
                "train.seed": seed,
                "train.workers": workers,
                "model.arch": arch,
                "model.num_points": num_points,
            }
        )
        if dump_config:
            typer.echo(cfg.to_yaml(), nl=False)
            return
        if out is None:
            raise InputError("give --out, the run directory", "--out")
        from pnvlad_service.training.train import train as run

        res = run(cfg, out, resume=resume, progress=progress)
        if res.model_dir is not None:
            typer.echo(res.summary())
