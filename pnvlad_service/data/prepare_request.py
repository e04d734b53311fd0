"""What one ``pnvlad data prepare`` asks of a drive, checked before a scan is read
(:class:`PrepareRequest`), the one call that runs it (:meth:`PrepareRequest.run`, which is
:func:`~pnvlad_service.data.prepare.prepare_drive`) and the lines that report the result.

The checks name the command's options (``--kind``, ``--test-stride``...) since that is where a
request comes from; the drive itself comes from :mod:`pnvlad_service.data.sources.registry`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from pnvlad_service.data.cuts import Kind, Layout
from pnvlad_service.data.prepare import PrepareResult, prepare_drive
from pnvlad_service.errors import InputError
from pnvlad_service.io.utm import normalize_zone
from pnvlad_service.preprocess.filter_g import GConfig, scan_config

if TYPE_CHECKING:
    from pnvlad_service.data.drive import Drive

#: ``--kind`` words that stand for several kinds.
KIND_ALIASES = {"both": "train,test", "all": "train,test,keyframe"}
KINDS: tuple[Kind, ...] = ("train", "test", "keyframe")


def parse_kinds(kind: str) -> tuple[Kind, ...]:
    """The kinds ``--kind`` asks for: ``train``, ``test``, ``keyframe``, a comma list of them,
    ``both`` (train and test) or ``all`` (the three), each once, in the order given."""
    kinds = tuple(dict.fromkeys(k.strip() for k in KIND_ALIASES.get(kind, kind).split(",")))
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise InputError(
            f"expected train, test, keyframe, a comma list of them, both or all, got {kind!r}",
            "--kind",
        )
    return kinds  # type: ignore[return-value]


def kind_strides(
    kinds: tuple[Kind, ...],
    stride: float | None = None,
    test_stride: float | None = None,
    keyframe_stride: float | None = None,
) -> dict[str, float]:
    """Kind -> stride (metres): ``stride`` for the first submap kind asked for, ``test_stride``
    for test (with both train and test only), ``keyframe_stride`` for keyframes; the kinds
    without one take their layout's."""
    submaps = [k for k in kinds if k != "keyframe"]
    if test_stride is not None and submaps != ["train", "test"]:
        raise InputError("--test-stride goes with --kind both (else use --stride)", "--kind")
    strides: dict[str, float] = {}
    if stride is not None and submaps:
        strides[submaps[0]] = stride
    if test_stride is not None:
        strides["test"] = test_stride
    if keyframe_stride is not None:
        if "keyframe" not in kinds:
            raise InputError("goes with --kind keyframe (or all)", "--keyframe-stride")
        strides["keyframe"] = keyframe_stride
    return strides


def keyframe_g(
    config: GConfig | None, kinds: tuple[Kind, ...], scan_range: float | None = None
) -> GConfig:
    """G of a keyframe: ``config`` (default G) as one scan's G
    (:func:`~pnvlad_service.preprocess.filter_g.scan_config`), cropped at ``scan_range`` metres
    from the sensor (default 50)."""
    if scan_range is not None and not scan_range > 0:
        raise InputError(f"must be a positive number of metres, got {scan_range}", "--scan-range")
    if scan_range is not None and "keyframe" not in kinds:
        raise InputError("goes with --kind keyframe (or all)", "--scan-range")
    return scan_config(config, scan_range) if scan_range else scan_config(config)


@dataclass(frozen=True)
class PrepareRequest:
    """The arguments of one :func:`~pnvlad_service.data.prepare.prepare_drive` call, checked
    (:meth:`checked` builds one from the command's options); see there for each field."""

    out: Path
    kinds: tuple[Kind, ...]
    layout: Layout = "oxford"
    strides_m: dict[str, float] = field(default_factory=dict)
    window_m: float | None = None
    box_m: float | None = None
    g_config: GConfig | None = None
    keyframe_config: GConfig = field(default_factory=scan_config)
    seed: int = 0
    max_points_per_scan: int | None = 10_000
    max_range_m: float | None = None
    scan_step: int = 1
    min_scan_spacing_m: float = 0.05
    raw_scans: bool = False
    resume: bool = False
    overwrite: bool = False
    utm_zone: str = ""

    @classmethod
    def checked(
        cls,
        out: Path | None,
        *,
        kind: str = "both",
        stride: float | None = None,
        test_stride: float | None = None,
        keyframe_stride: float | None = None,
        scan_range: float | None = None,
        g_config: str | Path | None = None,
        resume: bool = False,
        overwrite: bool = False,
        utm_zone: str | None = None,
        **settings: object,
    ) -> PrepareRequest:
        """The request of the options ``--kind``, ``--stride``, ``--test-stride``,
        ``--keyframe-stride``, ``--scan-range``, ``--g-config`` (a YAML or JSON file of G's
        settings), ``--resume``, ``--overwrite`` and ``--utm-zone``, checked in that order (the
        first wrong one is the :class:`InputError`); ``settings``: the other fields, as they
        are."""
        kinds = parse_kinds(kind)
        if out is None:
            raise InputError("missing: the run folder to write", "--out")
        config = None if g_config is None else GConfig.from_file(g_config)
        strides = kind_strides(kinds, stride, test_stride, keyframe_stride)
        keyframe_config = keyframe_g(config, kinds, scan_range)
        if resume and overwrite:
            raise InputError("--resume and --overwrite exclude each other", "--resume")
        zone = normalize_zone(utm_zone, "--utm-zone")
        return cls(
            out=Path(out),
            kinds=kinds,
            strides_m=strides,
            g_config=config,
            keyframe_config=keyframe_config,
            resume=resume,
            overwrite=overwrite,
            utm_zone=zone,
            **settings,  # type: ignore[arg-type]
        )

    def run(self, drive: Drive, *, progress: bool = True) -> PrepareResult:
        """Cut ``drive`` as asked (:func:`~pnvlad_service.data.prepare.prepare_drive`)."""
        return prepare_drive(
            drive,
            self.out,
            layout=self.layout,
            kinds=self.kinds,
            window_m=self.window_m,
            box_m=self.box_m,
            strides_m=self.strides_m,
            g_config=self.g_config,
            keyframe_config=self.keyframe_config,
            seed=self.seed,
            max_points_per_scan=self.max_points_per_scan,
            max_range_m=self.max_range_m,
            scan_step=self.scan_step,
            min_scan_spacing_m=self.min_scan_spacing_m,
            raw_scans=self.raw_scans,
            resume=self.resume,
            overwrite=self.overwrite,
            progress=progress,
            utm_zone=self.utm_zone,
        )


def report_lines(result: PrepareResult, scans: int) -> list[str]:
    """One line per kind (submaps, written, kept, failed) and one on speed, for ``scans`` scans
    in the drive."""
    lines = []
    for res in result.layouts:
        line = f"{res.kind:8s} {res.folder}: {res.submaps - res.failed} submaps"
        extra = [f"{res.written} written"]
        if res.resumed:
            extra.append(f"{res.resumed} kept")
        if res.failed:
            extra.append(f"{res.failed} failed (see log)")
        lines.append(f"{line} ({', '.join(extra)}), locations in {res.csv.name}")
    lines.append(
        f"{scans} scans ({result.scans_read} read) in {result.seconds:.1f} s, "
        f"{result.submaps_per_second():.2f} submaps/s"
    )
    return lines
