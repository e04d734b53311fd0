"""The ``pnvlad`` console script: one Typer app with a sub-command per job."""

from __future__ import annotations

import typer

from pnvlad_cli import common

app = typer.Typer(
    rich_markup_mode="markdown",
    name="pnvlad",
    help=(
        "LiDAR place recognition with PointNetVLAD: prepare benchmark data, train the encoder, "
        "build a FAISS index of your map and serve 'where am I?' over HTTP.\n\n"
        "Typical flow: pnvlad synth (or pnvlad data prepare) -> pnvlad data splits -> "
        "pnvlad train -> pnvlad eval -> pnvlad index build -> pnvlad serve."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        from pnvlad_service import __version__

        typer.echo(f"pnvlad {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: int = typer.Option(
        0, "--verbose", "-v", count=True, help="More log output (-vv for debug)."
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only warnings and errors."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    common.setup_logging(-1 if quiet else verbose)


def _register() -> None:
    # Imported here so each module stays importable on its own; none of them imports heavy
    # libraries at module level.
    from pnvlad_cli import data, evaluate, index, localize, map, model, serve, synth, train

    app.add_typer(data.app, name="data", rich_help_panel="Data")
    app.command("synth", rich_help_panel="Data")(synth.synth)
    app.command("train", rich_help_panel="Model")(train.train)
    app.command("eval", rich_help_panel="Model")(evaluate.evaluate)
    app.add_typer(model.app, name="model", rich_help_panel="Model")
    app.add_typer(map.app, name="map", rich_help_panel="Data")
    app.add_typer(index.app, name="index", rich_help_panel="Service")
    app.command("serve", rich_help_panel="Service")(serve.serve)
    app.command("localize", rich_help_panel="Service")(localize.localize)


_register()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
