"""The umbrella command line: `cpslam dataset …`, `cpslam eval …`.

Each command lives next to the code it drives (for example `cpslam.tools.synth.cli`) and
is only registered here, so that this file stays a table of contents. Heavy libraries
(torch, open3d) are imported inside the commands, which keeps `cpslam --help` fast.
"""

from __future__ import annotations

import typer

from cpslam import __version__
from cpslam.common.config.cli import presets as config_presets
from cpslam.common.config.cli import show as config_show
from cpslam.common.datasets.cli import info as dataset_info
from cpslam.common.logs import setup_logging
from cpslam.demo import demo
from cpslam.run import run as run_command
from cpslam.server.client import finalise as server_finalise
from cpslam.server.client import status as server_status
from cpslam.tools.eval.cli import ate as eval_ate
from cpslam.tools.eval.recon_cli import recon as eval_recon
from cpslam.tools.render import render
from cpslam.tools.synth.cli import synth as dataset_synth

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="cpslam — collaborative neural point-based RGB-D SLAM.",
    context_settings={"help_option_names": ["-h", "--help"]},
)
dataset_app = typer.Typer(no_args_is_help=True, help="Inspect and generate RGB-D sequences.")
eval_app = typer.Typer(no_args_is_help=True, help="Evaluate trajectories against ground truth.")
app.add_typer(dataset_app, name="dataset")
app.add_typer(eval_app, name="eval")
config_app = typer.Typer(no_args_is_help=True, help="Show the effective configuration and presets.")
app.add_typer(config_app, name="config")

dataset_app.command("info")(dataset_info)
dataset_app.command("synth")(dataset_synth)
eval_app.command("ate")(eval_ate)
eval_app.command("recon")(eval_recon)
config_app.command("show")(config_show)
app.command("render")(render)
app.command("run")(run_command)
app.command("demo")(demo)
app.command("status")(server_status)
app.command("finalise")(server_finalise)
config_app.command("presets")(config_presets)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cpslam {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output (-vv)."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
) -> None:
    setup_logging(verbose)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
