"""Commands of `pnvlad data` (see cli/data.py): check a benchmark tree, build and convert splits.

Library imports happen inside the commands so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from pnvlad_cli.common import progress_option, user_errors

if TYPE_CHECKING:
    from pnvlad_service.data.splits import Splits


def check(
    root: Path = typer.Argument(..., help="Tree root holding dataset folders (e.g. oxford/)."),
    deep: bool = typer.Option(
        False, "--deep", help="Also read every .bin and check its values are finite, in [-1, 1]."
    ),
    max_problems: int = typer.Option(50, help="Problems listed at most (all are counted)."),
    progress: bool = progress_option(),
) -> None:
    """Check a benchmark tree and print a summary.

    Prints, per dataset, the layout, runs, submaps of each role (train:
    pointcloud_20m_10overlap, test: pointcloud_20m, or the in-house
    names) and the UTM extent. Checks CSV headers and values (integers,
    finite numbers), duplicate timestamps, CSV rows without a .bin and
    .bin files without a row, .bin sizes (exactly 98,304 bytes), empty
    runs. Exits 1 listing the problems when there are any.

    Example:

        pnvlad data check benchmark_datasets/
    """
    from pnvlad_service.data.tree import check_tree, format_report

    with user_errors():
        report = check_tree(root, deep=deep, progress=progress)
    typer.echo(format_report(report, max_problems=max_problems))
    if not report.ok:
        raise typer.Exit(code=1)


_KIND = typer.Option(
    "submap",
    "--kind",
    help="submap (the 20 m submaps: train and test layouts; default ROOT/splits.json) or "
    "keyframe (the single-scan keyframe maps, for -c bev_scan/cpu_scan; default "
    "ROOT/splits_keyframes.json).",
)
_QUERY_RUN = typer.Option(
    None,
    "--query-run",
    help="A run held out as queries (repeatable): the training tuples come from every "
    "place of the other runs (the map) and none of these, no test regions needed; each "
    "query run is evaluated against the map runs. For a map of your own drives.",
)


def splits(
    root: Path = typer.Argument(..., help="Tree root holding dataset folders."),
    dataset: list[str] = typer.Option(
        None, "--dataset", "-d", help="Dataset folder to use (repeatable; default: all)."
    ),
    regions: Path = typer.Option(
        None,
        "--regions",
        help="Test regions file (JSON or CSV, docs/SPLITS.md). Default: ROOT/DATASET/"
        "test_regions.json, else the published regions (Oxford, in-house areas).",
    ),
    pos_radius: float = typer.Option(10.0, help="Positives: within this distance, m (<=)."),
    neg_radius: float = typer.Option(50.0, help="Negatives: beyond this distance, m (>)."),
    truth_radius: float = typer.Option(25.0, help="Evaluation ground truth: within, m (<=)."),
    out: Path = typer.Option(
        None, "--out", "-o", help="Splits file to write (default: ROOT/splits.json)."
    ),
    export_pickles: Path = typer.Option(
        None, "--export-pickles", help="Also write the published pickles into this folder."
    ),
    published_runs: bool = typer.Option(
        False,
        "--published-runs",
        help="Use the runs the published scripts picked (Oxford: train on all sorted runs but "
        "the last, evaluate on 23 of them; in-house: evaluate entries 1-14). Default: all runs.",
    ),
    kind: str = _KIND,
    query_run: list[str] = _QUERY_RUN,
    progress: bool = progress_option(),
) -> None:
    """Build training tuples and evaluation sets by the published rules.

    Training tuples: training-layout submaps outside the test regions,
    all runs of a dataset pooled; positives within --pos-radius (10 m),
    negatives beyond --neg-radius (50 m). Evaluation sets: per run, the
    database is every test-layout submap, the queries those inside the
    test regions; ground truth: other runs' database submaps within
    --truth-radius (25 m). Test regions: squares of +-150 m (strict)
    around given centres. Writes our JSON format (docs/SPLITS.md).

    With --query-run, a map of your own drives: training tuples from every
    place of the map runs, the query runs evaluated against them. Split the
    tree pnvlad map align wrote (ROOT-aligned), whose entries lie where the
    aligned poses put them, rather than the recorded one.

    Examples:

        pnvlad data splits benchmark_datasets/ -d oxford --export-pickles pickles/

        pnvlad data splits campus/ --kind keyframe --query-run 2026-05-04-run4
    """
    from pnvlad_service.data import splits as sp
    from pnvlad_service.errors import InputError

    with user_errors():
        if kind not in ("submap", "keyframe"):
            raise InputError(f"expected submap or keyframe, got {kind!r}", "--kind")
        if query_run and (regions or published_runs):
            raise InputError("test regions and published runs do not apply", "--query-run")
        reg = sp.load_regions(regions) if regions else None
        result = sp.build_splits(
            root,
            dataset or None,
            reg,
            pos_radius=pos_radius,
            neg_radius=neg_radius,
            truth_radius=truth_radius,
            published=published_runs,
            keyframes=kind == "keyframe",
            query_runs=query_run or None,
        )
        target = out or root / ("splits.json" if kind == "submap" else "splits_keyframes.json")
        sp.save_splits(target, result)
        _summary(result)
        typer.echo(f"wrote {target}")
        if export_pickles:
            for p in sp.export_pickles(result, export_pickles, progress=progress):
                typer.echo(f"wrote {p}")


def _summary(result: Splits) -> None:
    for name, t in result.training.items():
        test = result.test_tuples.get(name)
        typer.echo(
            f"{name}: {len(t)} training tuples ({len(t.anchors(2))} with >= 2 positives)"
            + (f", {len(test)} test tuples" if test is not None else "")
        )
    for name, es in result.evaluation.items():
        sizes = [len(d) for d in es.database]
        pairs = sum(
            1
            for j in range(len(es.runs))
            for i in es.truth[j]
            if any(len(x) for x in es.truth[j][i])
        )
        typer.echo(
            f"{name}: {len(es.runs)} runs, {sum(sizes)} database submaps, {es.n_queries()} "
            f"queries, {pairs} of {len(es.runs) * (len(es.runs) - 1)} run pairs with ground truth"
        )


def import_pickles(
    pickles: list[Path] = typer.Argument(
        ..., help="Published pickle files or folders holding them."
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Splits file to write (our JSON format)."),
) -> None:
    """Convert the published split pickles to our JSON, running no code.

    Reads training_queries_*.pickle, test_queries_*.pickle and
    NAME_evaluation_database / NAME_evaluation_query.pickle pairs
    with an unpickler that refuses every class (a file that names any
    class or function is rejected), checks their structure and indices.

    Example:

        pnvlad data import-pickles generating_queries/ -o splits.json
    """
    from pnvlad_service.data import splits as sp

    with user_errors():
        result = sp.import_pickles(pickles)
        sp.save_splits(out, result)
        _summary(result)
        typer.echo(f"wrote {out}")


def export_pickles(
    splits_file: Path = typer.Argument(..., help="Our splits JSON file."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the pickles."),
    progress: bool = progress_option(),
) -> None:
    """Write the published pickles from our splits file.

    Writes training_queries_baseline.pickle,
    test_queries_baseline.pickle (prefixed by the dataset when there are
    several) and NAME_evaluation_database/query.pickle, plain types.

    Example:

        pnvlad data export-pickles splits.json -o pickles/
    """
    from pnvlad_service.data import splits as sp

    with user_errors():
        for p in sp.export_pickles(sp.load_splits(splits_file), out, progress=progress):
            typer.echo(f"wrote {p}")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the `pnvlad data` group."""
    app.command("check")(check)
    app.command("splits")(splits)
    app.command("import-pickles")(import_pickles)
    app.command("export-pickles")(export_pickles)
