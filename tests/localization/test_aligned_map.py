"""Following on an aligned map (``pnvlad localize --aligned-map``): a scan registered near its
prior takes the nearest entries of any of the map's drives, not of one; how the follow, the
server's settings and the command say so, and what they refuse."""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.config import ALIGNED_ENTRIES, DriveConfig, ServiceConfig
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.prior import Prior
from pnvlad_service.server.settings import ServerSettings


def test_the_aligned_map_registers_to_any_drive_and_only_in_this_process(tmp_path) -> None:
    assert ServiceConfig(index=tmp_path).localizer_config() is None  # the shipped rules
    prior = ServiceConfig(index=tmp_path, aligned_map=True).localizer_config().prior.config()
    assert (prior.same_run, prior.max_submaps) == (False, ALIGNED_ENTRIES)
    config = DriveConfig(service={"url": "http://127.0.0.1:1", "aligned_map": True})
    with pytest.raises(InputError, match="PNVLAD_PRIOR_SAME_RUN") as exc:
        config.check()
    assert "--aligned-map" in str(exc.value)


def test_a_server_is_told_by_its_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    assert ServerSettings().prior_config().same_run is True
    monkeypatch.setenv("PNVLAD_PRIOR_SAME_RUN", "false")
    monkeypatch.setenv("PNVLAD_PRIOR_MAX_SUBMAPS", "8")
    got = ServerSettings().prior_config()
    assert (got.same_run, got.max_submaps) == (False, 8)


def test_the_command_refuses_it_where_it_does_not_apply() -> None:
    res = CliRunner().invoke(app, ["localize", "scan.bin", "--index", "map.index", "--aligned-map"])
    assert res.exit_code == 2 and "--aligned-map" in res.output


def test_a_prior_registers_to_several_drives_on_an_aligned_map(tiny_maps: dict) -> None:
    """The tiny city's keyframe map of its drives but one: near the held-out drive's scans, the
    entries registered to come from several drives with the aligned map's rules, from one
    without."""
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    drive = simulated_drive(get_preset("tiny"), 0, 0, 3)  # the held-out run of tiny_maps
    aligned = ServiceConfig(index=tiny_maps["keys"], aligned_map=True).localizer_config()
    runs_one, runs_any, entries_any = set(), set(), []
    with (
        Localizer.load(tiny_maps["keys"]) as one,
        Localizer.load(tiny_maps["keys"], config=aligned) as anyrun,
    ):
        for i in range(4, 40, 8):
            true = drive.true_poses[i]
            yaw = math.degrees(math.atan2(true[1, 0], true[0, 0]))
            prior = Prior(true[1, 3], true[0, 3], yaw, 20.0)
            a = one.localize(drive.scan(i), kind="scan", prior=prior).to_json()
            b = anyrun.localize(drive.scan(i), kind="scan", prior=prior, top_n=16).to_json()
            runs_one.add(len({m["run"] for m in a["matches"]}))
            runs_any.add(len({m["run"] for m in b["matches"]}))
            entries_any.append(len(b["matches"]))
    assert runs_one == {1}
    assert max(runs_any) >= 2, runs_any
    assert max(entries_any) > 4 and max(entries_any) <= ALIGNED_ENTRIES, entries_any
