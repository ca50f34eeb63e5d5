"""The umbrella command line: `cpslam dataset …`, `cpslam eval …`.

Each command lives next to the code it drives (for example `cpslam.tools.synth.cli`) and
is only registered here, so that this file stays a table of contents. Heavy libraries
(torch, open3d) are imported inside the commands, which keeps `cpslam --help` fast.
"""

from __future__ import annotations

from cpslam.common.cli import App
from cpslam.common.config.cli import presets as config_presets
from cpslam.common.config.cli import show as config_show
from cpslam.common.datasets.cli import gt as dataset_gt
from cpslam.common.datasets.cli import info as dataset_info
from cpslam.demo import demo
from cpslam.run import run as run_command
from cpslam.server.client import finalise as server_finalise
from cpslam.server.client import status as server_status
from cpslam.tools.eval.cli import ate as eval_ate
from cpslam.tools.eval.recon_cli import recon as eval_recon
from cpslam.tools.eval.render_cli import render as eval_render
from cpslam.tools.mesh_cli import mesh as mesh_command
from cpslam.tools.prior import prior as prior_command
from cpslam.tools.render import render
from cpslam.tools.report_cli import report as report_command
from cpslam.tools.secure.cli import init as secure_init
from cpslam.tools.synth.cli import synth as dataset_synth
from cpslam.tools.view.cli import view

app = App(
    no_args_is_help=True,
    epilog="The daemons are separate commands: cpslam-server (the collaboration back end) and "
    "cpslam-agent (one agent on one sequence); each has --help. Flags, exit codes and the "
    "overwrite rule: docs/cli.md.",
)
dataset_app = App(no_args_is_help=True, help="Inspect and generate RGB-D sequences.\n\n"
                  "Examples:\n\n  cpslam dataset info runs/data/room/agent_0 --json\n\n"
                  "  cpslam dataset synth --scene room --loop --out runs/data/room\n\n"
                  "  cpslam dataset gt runs/data/room/agent_0 --out gt.tum")
eval_app = App(no_args_is_help=True, help="Evaluate trajectories, meshes and renders against "
               "ground truth.\n\n"
               "Examples:\n\n  cpslam eval ate --gt runs/data/room/agent_0 --est runs/room\n\n"
               "  cpslam eval recon --gt data/synth/mesh.ply --est runs/x/mesh.ply --json")
app.add_typer(dataset_app, name="dataset")
app.add_typer(eval_app, name="eval")
config_app = App(no_args_is_help=True, help="Show the effective configuration and presets.\n\n"
                 "Examples:\n\n  cpslam config show --preset paper\n\n  cpslam config presets")
app.add_typer(config_app, name="config")
secure_app = App(no_args_is_help=True, help="Certificates and access control for a deployment.\n\n"
                 "Examples:\n\n  cpslam secure init --agents 2 --out secure")
app.add_typer(secure_app, name="secure")

dataset_app.command("info")(dataset_info)
dataset_app.command("synth")(dataset_synth)
dataset_app.command("gt")(dataset_gt)
eval_app.command("ate")(eval_ate)
eval_app.command("recon")(eval_recon)
eval_app.command("render")(eval_render)
config_app.command("show")(config_show)
app.command("render")(render)
app.command("view")(view)
app.command("report")(report_command)
app.command("mesh")(mesh_command)
app.command("prior")(prior_command)
app.command("run")(run_command)
app.command("demo")(demo)
app.command("status")(server_status)
app.command("finalise")(server_finalise)
config_app.command("presets")(config_presets)
secure_app.command("init")(secure_init)


@app.callback()
def _root() -> None:
    """cpslam — collaborative neural point-based RGB-D SLAM.

    Examples:

      cpslam demo

      cpslam dataset synth --scene room --loop --out runs/data/room

      cpslam run --seq runs/data/room/agent_0 -v

      cpslam status --connect tcp/127.0.0.1:7447 --json
    """


def main() -> None:
    app()


if __name__ == "__main__":
    main()
