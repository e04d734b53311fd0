"""Following on an aligned map: a scan registered near its prior takes the nearest entries of
any of the map's drives, not of one, and a fit under the threshold is tried once more against a
wider stretch; a bundle that records its map as aligned (``pnvlad index build`` of a tree ``map
align`` wrote) gets these rules by default, an explicit option or setting overrides them both
ways; what the follow and the command refuse."""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.config import DriveConfig, ServiceConfig
from pnvlad_service.localization.query.config import LocalizerConfig, PriorSection
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.prior import (
    ALIGNED_ENTRIES,
    ALIGNED_RETRY_ENTRIES,
    Prior,
    PriorConfig,
)
from pnvlad_service.server.settings import ServerSettings

ONE_DRIVE = (True, PriorConfig.max_submaps, 0)
ANY_DRIVE = (False, ALIGNED_ENTRIES, ALIGNED_RETRY_ENTRIES)


def rules(config: PriorConfig) -> tuple[bool, int, int]:
    return config.same_run, config.max_submaps, config.retry_submaps


def test_the_option_says_it_both_ways_and_only_in_this_process(tmp_path) -> None:
    assert ServiceConfig(index=tmp_path).localizer_config() is None  # the bundle says
    for given, want in ((True, ANY_DRIVE), (False, ONE_DRIVE)):
        section = ServiceConfig(index=tmp_path, aligned_map=given).localizer_config().prior
        assert rules(section.config(aligned=True)) == want == rules(section.config(False))
    for given in (True, False):
        config = DriveConfig(service={"url": "http://127.0.0.1:1", "aligned_map": given})
        with pytest.raises(InputError, match="PNVLAD_PRIOR_ALIGNED_MAP") as exc:
            config.check()
        assert "--aligned-map" in str(exc.value)


def test_the_bundle_sets_the_default_and_an_explicit_config_wins(
    tiny_maps: dict, tiny_aligned: dict
) -> None:
    one = LocalizerConfig(prior=PriorSection(same_run=True, max_submaps=4, retry_submaps=0))
    anyrun = LocalizerConfig(prior=PriorSection(same_run=False, max_submaps=8, retry_submaps=24))
    for bundle, aligned in ((tiny_aligned["keys"], True), (tiny_maps["keys"], False)):
        with Localizer.load(bundle) as loc:
            assert loc.aligned_map is aligned
            assert rules(loc.prior_config) == (ANY_DRIVE if aligned else ONE_DRIVE)
        for config, want in ((one, ONE_DRIVE), (anyrun, ANY_DRIVE)):
            with Localizer.load(bundle, config=config) as loc:
                assert rules(loc.prior_config) == want
        # Taken the other way round than the bundle records: every rule follows, and says so.
        other = LocalizerConfig(prior=PriorSection(aligned_map=not aligned))
        with Localizer.load(bundle, config=other) as loc:
            assert loc.aligned_map is (not aligned)
            assert rules(loc.prior_config) == (ONE_DRIVE if aligned else ANY_DRIVE)


def test_a_server_follows_its_bundle_unless_its_settings_say(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert rules(ServerSettings().prior_config()) == ONE_DRIVE
    assert rules(ServerSettings().prior_config(aligned=True)) == ANY_DRIVE
    monkeypatch.setenv("PNVLAD_PRIOR_SAME_RUN", "true")
    monkeypatch.setenv("PNVLAD_PRIOR_RETRY_SUBMAPS", "0")
    assert rules(ServerSettings().prior_config(aligned=True)) == (True, ALIGNED_ENTRIES, 0)
    monkeypatch.setenv("PNVLAD_PRIOR_SAME_RUN", "false")
    monkeypatch.setenv("PNVLAD_PRIOR_MAX_SUBMAPS", "8")
    monkeypatch.delenv("PNVLAD_PRIOR_RETRY_SUBMAPS")
    assert rules(ServerSettings().prior_config()) == (False, 8, 0)
    for name in ("PNVLAD_PRIOR_SAME_RUN", "PNVLAD_PRIOR_MAX_SUBMAPS"):
        monkeypatch.delenv(name)
    monkeypatch.setenv("PNVLAD_PRIOR_ALIGNED_MAP", "true")
    assert rules(ServerSettings().prior_config(aligned=False)) == ANY_DRIVE
    monkeypatch.setenv("PNVLAD_PRIOR_ALIGNED_MAP", "false")
    assert rules(ServerSettings().prior_config(aligned=True)) == ONE_DRIVE


@pytest.mark.parametrize("flag", ["--aligned-map", "--no-aligned-map"])
def test_the_command_refuses_it_where_it_does_not_apply(flag: str) -> None:
    res = CliRunner().invoke(app, ["localize", "scan.bin", "--index", "map.index", flag])
    assert res.exit_code == 2 and "--aligned-map" in res.output


def test_a_prior_registers_to_several_drives_on_an_aligned_map(tiny_maps: dict) -> None:
    """The tiny city's keyframe map of its drives but one: near the held-out drive's scans, the
    entries registered to come from several drives with the aligned map's rules, from one
    without."""
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    drive = simulated_drive(get_preset("tiny"), 0, 0, 3)  # the held-out run of tiny_maps
    aligned = LocalizerConfig(prior=PriorSection(same_run=False, max_submaps=8, retry_submaps=0))
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
