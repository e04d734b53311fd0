"""synth.preview: the map and the before/after submap figures are PNGs."""

from __future__ import annotations

from pathlib import Path


def test_render_previews_writes_the_map_and_one_submap_figure_per_area(
    tiny: Path, tmp_path: Path
) -> None:
    from pnvlad_service.synth.preview import render_previews

    paths = render_previews(tiny, tmp_path / "png")
    assert [p.name for p in paths] == ["map.png", "submap_business.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
