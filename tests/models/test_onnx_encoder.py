"""models.onnx_encoder and models.runtimes: which session runs which clouds (the crowded
encoder's rule, as torch's ``Encoder`` has it), concurrent callers, input checks, and which
runtime a model directory gets."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.models import runtimes
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.onnx_encoder import OnnxEncoder, cosines
from pnvlad_service.models.onnx_export import export_onnx
from pnvlad_service.models.store import save_model
from tests.models.helpers import CONFIGS, clouds, trained_like


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("onnx") / "m"
    cfg = CONFIGS["compact"]
    save_model(d, trained_like(cfg), cfg)
    export_onnx(d)
    return d


def _spy(enc: OnnxEncoder) -> list[tuple[str, int]]:
    """Record (session, clouds) of every run of ``enc``."""
    calls: list[tuple[str, int]] = []
    run = enc._run

    def spy(session, x):
        calls.append(("wide" if session is enc._wide else "narrow", len(x)))
        return run(session, x)

    enc._run = spy  # type: ignore[method-assign]
    return calls


def test_sessions_split_a_batch_as_the_torch_encoder_does(model_dir: Path) -> None:
    """A lone cloud on idle cores: the wide session. Several: the workers, one share each; the
    last clouds that would leave most workers idle: the wide session. Crowded: all on the
    workers. The descriptors are the same whichever way, and in batch order."""
    enc = OnnxEncoder.from_checkpoint(model_dir, threads=2)
    want = Encoder.from_checkpoint(model_dir).embed(clouds(5, n=4096, seed=1).numpy())
    calls = _spy(enc)
    x = clouds(5, n=4096, seed=1).numpy()
    for b, expect in [
        (1, [("wide", 1)]),
        (2, [("narrow", 1), ("narrow", 1)]),
        (3, [("narrow", 1), ("narrow", 1), ("wide", 1)]),  # 3 % 2 = 1 <= 2 / 2
        (4, [("narrow", 2), ("narrow", 2)]),
    ]:
        calls.clear()
        got = enc.embed(x[:b])
        assert sorted(calls) == sorted(expect), b
        assert cosines(got, want[:b]).min() >= 0.9999
    enc.crowded_by = lambda: True
    for b, expect in [(1, [("narrow", 1)]), (3, [("narrow", 2), ("narrow", 1)])]:
        calls.clear()
        got = enc.embed(x[:b])
        assert sorted(calls) == sorted(expect), b
        assert cosines(got, want[:b]).min() >= 0.9999
    enc.close()


def test_concurrent_callers_get_their_own_descriptors(model_dir: Path) -> None:
    """Two threads embedding at once (two batcher lanes): each gets its own clouds' descriptors;
    while the other is embedding, even a lone cloud goes to the workers."""
    enc = OnnxEncoder.from_checkpoint(model_dir, threads=2)
    x = clouds(6, n=1024, seed=3).numpy()
    want = enc.embed(x)
    results: dict[int, np.ndarray] = {}
    barrier = threading.Barrier(2)

    def call(i: int) -> None:
        barrier.wait()
        for _ in range(5):
            results[i] = enc.embed(x[i * 3 : i * 3 + 1 + i * 2])

    threads = [threading.Thread(target=call, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert np.allclose(results[0], want[0:1], atol=1e-6)
    assert np.allclose(results[1], want[3:6], atol=1e-6)
    enc.close()


def test_bad_points_are_refused(model_dir: Path) -> None:
    enc = OnnxEncoder.from_checkpoint(model_dir, threads=1, check=False)
    with pytest.raises(InputError, match=r"\[B, N, 3\]"):
        enc.embed(np.zeros((2, 10, 4), np.float32))
    with pytest.raises(InputError, match="NaN"):
        enc.embed(np.full((10, 3), np.nan, np.float32))
    with pytest.raises(InputError, match="float coordinates"):
        enc.embed(np.zeros((10, 3), bool))
    got = enc.embed(clouds(1, seed=2)[0])  # [N, 3], a torch tensor too
    assert got.shape == (1, enc.dim)


def test_choose_runtime(model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plain = tmp_path / "plain"
    cfg = CONFIGS["compact"]
    save_model(plain, trained_like(cfg), cfg)
    assert runtimes.choose_runtime(model_dir) == "torch"  # torch is installed here
    assert runtimes.choose_runtime(model_dir, "onnx") == "onnx"
    with pytest.raises(InputError, match=r"no model\.onnx"):
        runtimes.choose_runtime(plain, "onnx")
    with pytest.raises(InputError, match="runtime must be one of"):
        runtimes.choose_runtime(plain, "tensorflow")
    monkeypatch.setattr(runtimes, "torch_installed", lambda: False)
    assert runtimes.choose_runtime(model_dir) == "onnx"
    with pytest.raises(InputError, match=r"torch is not installed .* \(pnvlad model export "):
        runtimes.choose_runtime(plain)
    with pytest.raises(MissingDependencyError, match=r"pip install 'pnvlad\[torch\]'"):
        runtimes.choose_runtime(model_dir, "torch")
    enc = runtimes.open_encoder(model_dir)
    assert enc.runtime == "onnx" and "onnxruntime" in runtimes.describe(enc)
    with pytest.raises(InputError, match="runs on the CPU"):
        runtimes.open_encoder(model_dir, device="cuda")
