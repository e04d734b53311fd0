"""The compatibility check (localization/query/compatibility.py): the model a bundle is loaded with
is the one whose weights built it."""

from __future__ import annotations

import shutil

import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.compatibility import checked_model
from pnvlad_service.localization.query.localizer import Localizer
from tests.index.helpers import make_checkpoint


def test_checked_model_takes_a_run_directory_and_refuses_other_weights(world, tmp_path) -> None:
    bundle = world["bundle"]
    recorded = checked_model(bundle)
    assert recorded.checkpoint == str(world["ckpt"].resolve())
    run = tmp_path / "run"
    shutil.copytree(world["ckpt"], run / "model")
    via_run = checked_model(bundle, run)
    assert via_run.checkpoint == str((run / "model").resolve())
    assert via_run.weights_sha256 == recorded.weights_sha256
    other = make_checkpoint(tmp_path / "other", seed=3)
    with pytest.raises(InputError, match="other weights") as info:
        Localizer.load(bundle, other)
    assert str(bundle / "manifest.json") in str(info.value)
    assert str(other.resolve() / "model.safetensors") in str(info.value)


def test_the_localizer_module_still_names_it() -> None:
    from pnvlad_service.localization.query import localizer

    assert localizer.checked_model is checked_model
