"""training.runtime: one process is a world of one whose collectives are plain values."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.training.config import TrainSection
from pnvlad_service.training.runtime import (
    Dist,
    any_rank,
    gather_rows,
    mean_over_ranks,
    pick_device,
    restore_rng_state,
    rng_state_tensors,
    setup_runtime,
    wrap_ddp,
)

torch = pytest.importorskip("torch")


def test_one_process_on_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    before = torch.get_num_threads()
    try:
        rt = setup_runtime(TrainSection(device="cpu", threads=1, amp="bf16"))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    assert rt.dist == Dist() and rt.dist.main
    assert rt.device == torch.device("cpu")
    from pnvlad_service.models.inference import bf16_supported

    # bf16 on the CPU only where it is native
    assert rt.amp_dtype == (torch.bfloat16 if bf16_supported() else None)
    assert any_rank(True, rt) is True and any_rank(False, rt) is False
    assert mean_over_ranks(2.5, rt) == 2.5
    rows = np.arange(12, dtype=np.float32).reshape(4, 3)
    assert gather_rows(rows, 4, rt) is rows
    model = torch.nn.Linear(3, 2)
    assert wrap_ddp(model, rt) is model


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_names_the_option() -> None:
    with pytest.raises(InputError, match="CUDA requested") as err:
        pick_device("cuda", Dist())
    assert err.value.source == "train.device"
    assert pick_device("auto", Dist()) == torch.device("cpu")


def test_rng_state_round_trip() -> None:
    saved = rng_state_tensors()
    a = torch.rand(5)
    torch.rand(3)  # move on
    restore_rng_state(saved)
    assert torch.equal(torch.rand(5), a)


def test_cpu_bf16_only_when_native_and_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    import pnvlad_service.models.inference as inference

    monkeypatch.delenv("WORLD_SIZE", raising=False)
    before = torch.get_num_threads()
    try:
        for native, amp, want in [
            (True, "bf16", torch.bfloat16),
            (False, "bf16", None),
            (True, "auto", None),
            (True, "off", None),
        ]:
            monkeypatch.setattr(inference, "bf16_supported", lambda native=native: native)
            rt = setup_runtime(TrainSection(device="cpu", threads=1, amp=amp))
            assert rt.amp_dtype == want, (native, amp)
    finally:
        torch.set_num_threads(before)
