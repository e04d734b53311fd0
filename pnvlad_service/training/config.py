"""Training configuration: one pydantic model with ``model:``, ``train:`` and ``data:`` sections.

A config file (YAML or TOML) holds any subset of the fields; everything missing takes the
defaults below, which follow the paper's set-up (Uy & Lee, CVPR 2018, and its published code):
Adam at 5e-5 with a staircase decay, lazy quadruplet loss (alpha 0.5, beta 0.2), tuples of
1 anchor, 2 positives, 18 negatives and 1 other negative, hard negatives from a descriptor cache
refreshed every 700 steps. ``pnvlad train --dump-config`` prints them.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.training.augment import AugmentSection

LossName = Literal["lazy_quadruplet", "lazy_triplet", "quadruplet", "triplet"]


class TrainSection(BaseModel):
    """How to train: optimiser, schedule, tuples, mining, budget, checkpoints."""

    model_config = ConfigDict(extra="forbid")

    epochs: int = Field(20, ge=1, description="Passes over the training anchors.")
    batch_size: int = Field(
        2, ge=1, description="Tuples a step (tuple mode) or anchors a step (in-batch mode)."
    )
    lr: float = Field(5e-5, gt=0, description="Base learning rate of Adam.")
    lr_decay_rate: float = Field(0.7, gt=0, le=1, description="Staircase decay factor.")
    lr_decay_samples: int = Field(
        200_000, ge=1, description="Tuples seen between two learning-rate decays."
    )
    lr_min: float = Field(1e-5, ge=0, description="Floor of the learning rate.")
    lr_schedule: Literal["staircase", "cosine"] = Field(
        "staircase",
        description="'staircase': the paper's decay by tuples seen; 'cosine': from lr down to "
        "lr_min over the run's epochs.",
    )
    warmup_steps: int = Field(
        0, ge=0, description="Steps over which the learning rate climbs linearly to lr."
    )
    weight_decay: float = Field(0.0, ge=0)
    bn_init_decay: float = Field(0.5, description="1 - initial BN momentum (TF convention).")
    bn_decay_rate: float = Field(0.5, description="Staircase factor of the BN momentum.")
    bn_decay_samples: int = Field(200_000, ge=1, description="Tuples between BN decays.")
    bn_decay_clip: float = Field(0.99, description="Ceiling of the TF BN decay.")
    loss: LossName = "lazy_quadruplet"
    margin1: float = Field(0.5, description="alpha: anchor-positive vs anchor-negative margin.")
    margin2: float = Field(0.2, description="beta: anchor-positive vs negative-other margin.")
    positives: int = Field(2, ge=1, description="Positives a tuple.")
    negatives: int = Field(18, ge=1, description="Negatives a tuple.")
    mining: Literal["tuple", "in_batch"] = Field(
        "tuple",
        description=(
            "'tuple': the paper's tuples with cached hard negatives; 'in_batch': a batch of "
            "anchors and one positive each, every other batch member a candidate negative."
        ),
    )
    hard_negatives: int = Field(10, ge=0, description="Hardest cached negatives a tuple.")
    sampled_negatives: int = Field(
        3000, ge=1, description="Random negatives searched for the hardest ones."
    )
    cache_warmup_epochs: int = Field(
        1, ge=0, description="Epochs with random negatives before the first cache."
    )
    cache_refresh_steps: int = Field(700, ge=1, description="Steps between cache refreshes.")
    seed: int = 0
    device: str = Field("auto", description="'auto' (cuda when present), 'cpu', 'cuda', 'cuda:1'.")
    amp: Literal["auto", "off", "bf16", "fp16"] = Field(
        "auto",
        description="Mixed precision on CUDA ('auto': bf16 when supported, else fp16); on the "
        "CPU only 'bf16', and only where the CPU has native bfloat16.",
    )
    threads: int = Field(0, ge=0, description="torch CPU threads (0: the cores of this process).")
    workers: int = Field(4, ge=0, description="Threads loading submaps into RAM.")
    max_minutes: float | None = Field(None, gt=0, description="Wall-clock budget of the run.")
    init: str | None = Field(
        None,
        description="Weights to start from (fine-tuning): pretrained:NAME, a model directory, a "
        "training run, or a .safetensors/.pt file; they must fit model.* (training/init.py). "
        "None: random weights.",
    )
    max_steps: int | None = Field(None, ge=1, description="Stop after this many steps.")
    checkpoint_every: int = Field(500, ge=1, description="Steps between checkpoints.")
    keep_checkpoints: int = Field(2, ge=1, description="Step checkpoints kept on disk.")
    val_every: int = Field(1000, ge=0, description="Steps between validation recalls (0: off).")
    log_every: int = Field(10, ge=1, description="Steps between metrics-log lines.")
    resample_points: bool = Field(
        False,
        description="Hold each training submap whole and draw its model.num_points afresh each "
        "time it is embedded (False: one fixed subset a submap, as the published code).",
    )
    turned_negatives: bool = Field(
        False,
        description="In-batch mining: each member embedded a second time, turned by a random "
        "quarter turn, and those copies added to the other members' negatives: for models "
        "whose map holds four turns of every entry (model.canonical_heading), so that a place "
        "turned a quarter does not pass for another.",
    )
    augment: AugmentSection = Field(
        default_factory=AugmentSection,
        description="Perturbations of each training cloud (training/augment.py); off by default.",
    )


class DataSection(BaseModel):
    """Where the data is: a benchmark tree and its splits."""

    model_config = ConfigDict(extra="forbid")

    root: Path | None = Field(None, description="Benchmark tree (holds oxford/, inhouse_...).")
    splits: Path | None = Field(None, description="Splits JSON (pnvlad data splits).")
    pickles: Path | None = Field(None, description="Folder of the published pickles instead.")
    val_max_runs: int = Field(4, ge=2, description="Runs used by the periodic validation.")
    dataset_weights: dict[str, Annotated[float, Field(ge=0, allow_inf_nan=False)]] = Field(
        default_factory=dict,
        description="How often an epoch visits each dataset's anchors, by dataset folder name "
        "(1: once, the default; 3: three times; 0.5: a seeded half of them; 0: never, its "
        "submaps still negatives): to keep a small dataset's share when trees are mixed.",
    )


class TrainConfig(BaseModel):
    """Every field of a training run."""

    model_config = ConfigDict(extra="forbid")

    model: ModelConfig = Field(default_factory=ModelConfig.paper)
    train: TrainSection = Field(default_factory=TrainSection)
    data: DataSection = Field(default_factory=DataSection)

    @model_validator(mode="after")
    def _check(self) -> TrainConfig:
        if self.train.hard_negatives > self.train.negatives:
            raise ValueError("train.hard_negatives must not exceed train.negatives")
        return self

    @classmethod
    def preset(cls, name: str) -> TrainConfig:
        """A shipped config: ``paper``, ``compact``, ``cpu`` or ``bev``
        (pnvlad_service/configs/)."""
        folder = resources.files("pnvlad_service") / "configs"
        ref = folder / f"{name}.yaml"
        if not ref.is_file():
            names = sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))
            raise InputError(
                f"no shipped config named {name!r} ({', '.join(names)})", source="config"
            )
        return cls.from_mapping(_parse(ref.read_text(encoding="utf-8"), f"{name}.yaml"), name)

    @classmethod
    def from_file(cls, path: str | Path) -> TrainConfig:
        """Read a YAML (``.yaml``/``.yml``) or TOML (``.toml``) config; missing fields default."""
        path = Path(path)
        if not path.is_file():
            # A bare name picks a shipped preset.
            if path.suffix == "" and len(path.parts) == 1:
                return cls.preset(str(path))
            raise InputError("config file not found", source=path)
        return cls.from_mapping(_parse(path.read_text(encoding="utf-8"), path.name), path)

    @classmethod
    def from_mapping(cls, data: Any, source: str | Path = "config") -> TrainConfig:
        """Validate a nested mapping; raise InputError naming the bad field."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise InputError("a config is a mapping with model/train/data sections", source)
        data = dict(data)
        if "base" in data:
            # ``base: cpu`` starts from a shipped config; the sections given here override
            # its fields one by one (a model preset given here replaces its model).
            parent = cls.preset(str(data.pop("base"))).model_dump()
            model = data.get("model")
            if isinstance(model, dict) and "preset" in model:
                parent.pop("model")
            data = _merged(parent, data)
        model = data.get("model")
        if isinstance(model, dict) and "preset" in model:
            # ``model: {preset: compact, num_points: 1024}`` starts from a shipped model config.
            model = dict(model)
            name = str(model.pop("preset"))
            if name not in _MODEL_PRESETS:
                raise InputError(
                    f"model.preset: no model preset {name!r} ({', '.join(_MODEL_PRESETS)})", source
                )
            base = getattr(ModelConfig, name)()
            data["model"] = {**base.model_dump(), **model}
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            field = ".".join(str(p) for p in err["loc"])
            raise InputError(f"{field}: {err['msg']}", source=source) from None

    def with_overrides(self, overrides: dict[str, Any]) -> TrainConfig:
        """Return a copy with dotted fields (``"train.lr"``, ``"train.augment.yaw_deg"``)
        replaced; ``None`` values ignored."""
        data = self.model_dump()
        for key, value in overrides.items():
            if value is None:
                continue
            *sections, field = key.split(".")
            node = data
            for name in sections:
                node = node.get(name) if isinstance(node, dict) else None
            if not sections or not isinstance(node, dict) or field not in node:
                raise InputError(f"unknown config field {key!r}", source=key)
            node[field] = value
        return TrainConfig.from_mapping(data, "command line")

    def to_yaml(self) -> str:
        """The config as YAML text (every field)."""
        import yaml

        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


#: Model presets a config's ``model: {preset: NAME}`` may start from (``ModelConfig.NAME()``).
_MODEL_PRESETS = ("paper", "port", "compact", "bev")


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over``'s fields, mappings merged field by field."""
    out = dict(base)
    for key, value in over.items():
        old = out.get(key)
        both = isinstance(old, dict) and isinstance(value, dict)
        out[key] = _merged(old, value) if both else value
    return out


def run_config(config: str | Path | None, resumed_run: Path | None = None) -> TrainConfig:
    """The config a run starts from: ``config`` (a file or a shipped preset name) when given;
    else, when resuming ``resumed_run``, the ``config.yaml`` that run wrote; else the paper's."""
    if config is not None:
        return TrainConfig.from_file(config)
    if resumed_run is not None and (Path(resumed_run) / "config.yaml").is_file():
        return TrainConfig.from_file(Path(resumed_run) / "config.yaml")
    return TrainConfig.preset("paper")


def parse_assignments(assignments: list[str]) -> dict[str, Any]:
    """``["model.output_dim=128", "train.augment.yaw_deg=0"]`` -> ``{field: value}``, each value
    read as a YAML scalar or list (``128`` an int, ``true`` a bool, ``[64, 128]`` a list)."""
    import yaml

    out: dict[str, Any] = {}
    for text in assignments:
        key, eq, value = text.partition("=")
        if not eq or not key.strip():
            raise InputError(f"{text!r} is not FIELD=VALUE (e.g. model.output_dim=128)", "--set")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise InputError(
                f"{key.strip()}: {value!r} is not a YAML value ({exc})", "--set"
            ) from None
    return out


def _parse(text: str, name: str) -> Any:
    try:
        if name.endswith(".toml"):
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise InputError("TOML configs need Python 3.11; use YAML", source=name) from None
            return tomllib.loads(text)
        import yaml

        return yaml.safe_load(text)
    except Exception as exc:  # yaml.YAMLError / tomllib.TOMLDecodeError
        raise InputError(f"cannot parse config: {exc}", source=name) from None
