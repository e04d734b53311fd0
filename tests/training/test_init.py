"""`pnvlad train --init`: a run starts from the weights of a shipped model, an earlier run or a
weights file, read safely; weights that do not fit the run's config are one line naming the
layer, before anything is read or written."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from typer.testing import CliRunner  # noqa: E402

from pnvlad_cli.main import app  # noqa: E402
from pnvlad_service.errors import InputError  # noqa: E402
from pnvlad_service.models import pretrained  # noqa: E402
from pnvlad_service.models.packaging import Card, package_model  # noqa: E402
from pnvlad_service.models.store import load_model  # noqa: E402
from pnvlad_service.training.init import initial_weights  # noqa: E402
from pnvlad_service.training.train import train  # noqa: E402
from tests.training.street import tiny_config  # noqa: E402


def _start_weights(cfg, out: Path) -> dict[str, torch.Tensor]:
    """The weights a run of one step starts from (seen by the on_model hook)."""
    seen: dict[str, torch.Tensor] = {}

    def on_model(model: torch.nn.Module) -> None:
        seen.update({k: v.detach().clone() for k, v in model.state_dict().items()})

    threads = torch.get_num_threads()
    try:
        train(cfg, out, progress=False, on_model=on_model)
    finally:
        torch.set_num_threads(threads)
    return seen


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], atol: float = 0.0) -> bool:
    return a.keys() == b.keys() and all(
        torch.allclose(a[k].float(), b[k].float(), atol=atol, rtol=0) for k in a
    )


@pytest.fixture(scope="module")
def first(tiny_tree: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run of 2 steps on the tiny tree: the model to start from."""
    root, splits = tiny_tree
    out = tmp_path_factory.mktemp("init") / "first"
    threads = torch.get_num_threads()
    try:
        train(tiny_config(root, splits, max_steps=2), out, progress=False)
    finally:
        torch.set_num_threads(threads)
    return out


def test_a_run_starts_from_an_earlier_run_and_a_weights_file(
    first: Path, tiny_tree: tuple[Path, Path], tmp_path: Path
) -> None:
    root, splits = tiny_tree
    model, _ = load_model(first / "model")
    final = model.state_dict()
    # seed 1, so its random start is not the first run's either
    fresh = _start_weights(tiny_config(root, splits, max_steps=1, seed=1), tmp_path / "fresh")
    assert not _same(fresh, final)
    for i, ref in enumerate([first, first / "model", first / "model" / "model.safetensors"]):
        cfg = tiny_config(root, splits, max_steps=1, seed=1, init=str(ref))
        assert _same(_start_weights(cfg, tmp_path / f"tuned{i}"), final)
    # a torch file holding a state dict, bare or under "state_dict", read weights only
    torch.save({"state_dict": final, "epoch": 3}, tmp_path / "w.pth")
    assert _same(initial_weights(tiny_config(root, splits).model, tmp_path / "w.pth"), final)
    config = yaml_of(tmp_path / "tuned0" / "config.yaml")
    assert config["train"]["init"] == str(first)


def yaml_of(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text())


def test_a_shipped_model_by_name(first: Path, tiny_tree, tmp_path: Path, monkeypatch) -> None:
    root, splits = tiny_tree
    cat = tmp_path / "pretrained" / "catalogue.json"
    cat.parent.mkdir()
    cat.write_text(json.dumps({"format": "pnvlad-pretrained", "version": 1, "models": []}))
    monkeypatch.setenv(pretrained.CATALOGUE_ENV, str(cat))
    package_model(first / "model", "tiny-street", Card(kind="submap", trained_with="t", data="d"))
    final = load_model(first / "model")[0].state_dict()
    cfg = tiny_config(root, splits, max_steps=1, seed=1, init="pretrained:tiny-street")
    # stored in float16: the start is the first run's weights to float16's precision
    start = _start_weights(cfg, tmp_path / "tuned")
    assert _same(start, final, atol=2e-3) and not _same(start, final)
    cfg = tiny_config(root, splits, max_steps=1, init="pretrained:nope")
    with pytest.raises(InputError, match="nope"):
        train(cfg, tmp_path / "nope", progress=False)
    assert not (tmp_path / "nope").exists()


def test_weights_of_another_config_name_the_layer_and_write_nothing(
    first: Path, tiny_tree: tuple[Path, Path], tmp_path: Path
) -> None:
    root, splits = tiny_tree
    cfg = tiny_config(root, splits, max_steps=1, init=str(first))
    wider = cfg.model_copy(update={"model": cfg.model.model_copy(update={"output_dim": 16})})
    with pytest.raises(InputError) as err:
        train(wider, tmp_path / "run", progress=False)
    text = str(err.value)
    assert text.startswith("--init: ") and "\n" not in text
    assert "layer " in text and "(16, " in text and "(32, " in text  # this config's, the file's
    assert not (tmp_path / "run").exists()
    res = CliRunner().invoke(
        app,
        ["train", "-c", "bev", "--init", str(first), "--root", str(root), "--splits",
         str(splits), "-o", str(tmp_path / "cli")],
    )  # fmt: skip
    assert res.exit_code == 2 and "--init: " in res.output and "layer " in res.output
    assert [x for x in res.output.splitlines() if x.startswith("error:")] == [
        res.output.strip().splitlines()[-1]
    ]
    assert not (tmp_path / "cli").exists()


class Payload:
    """Something a full pickle would construct (and could run code in)."""

    def __reduce__(self):
        return (print, ("a pickle ran code",))


def test_a_torch_file_is_read_weights_only(tmp_path: Path, tiny_tree) -> None:
    root, splits = tiny_tree
    cfg = tiny_config(root, splits).model
    with open(tmp_path / "evil.pt", "wb") as fh:
        pickle.dump({"state_dict": Payload()}, fh)
    with pytest.raises(InputError, match=r"evil\.pt: not a weights-only torch file"):
        initial_weights(cfg, tmp_path / "evil.pt")
    torch.save({"step": 3}, tmp_path / "nothing.pt")
    with pytest.raises(InputError, match="holds no state dict"):
        initial_weights(cfg, tmp_path / "nothing.pt")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match=r"^--init: expected a model directory"):
        initial_weights(cfg, tmp_path / "notes.txt")
