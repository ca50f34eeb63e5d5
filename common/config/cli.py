"""Command-line pieces shared by every command that takes a configuration.

The option types below are used by `cpslam config show`, `cpslam-agent`, `cpslam-server`,
`cpslam run` and `cpslam demo`, so the same flags mean the same thing everywhere.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

PresetOpt = Annotated[
    str,
    typer.Option("--preset", "-p", help="Preset: paper (the paper as written, GPU), gpu (the "
                 "defaults, GPU), cpu (2-core CPU) or tiny (tests)."),
]
ConfigOpt = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML file applied over the preset.", dir_okay=False),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", "-s", help="Override a key, e.g. --set tracking.iters=50 (repeatable)."),
]
DeviceOpt = Annotated[
    str | None, typer.Option("--device", help="auto, cpu, cuda or cuda:N (overrides run.device).")
]
SeedOpt = Annotated[int | None, typer.Option(
    "--seed", help="The run's random seed (overrides run.seed).")]


def config_or_exit(
    preset: str,
    config_file: Path | None,
    sets: list[str] | None,
    device: str | None = None,
    seed: int | None = None,
):
    """Load the effective configuration, or print the error and exit with status 2."""
    from cpslam.common.cli import fail
    from cpslam.common.config import ConfigError, config_from_cli

    try:
        return config_from_cli(preset, config_file, sets or [], device=device, seed=seed)
    except ConfigError as err:
        fail(str(err))


def show(
    preset: PresetOpt = "cpu",
    config_file: ConfigOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = None,
    seed: SeedOpt = None,
) -> None:
    """Print the effective configuration as YAML (what a run would use).

    Examples:

      cpslam config show --preset paper

      cpslam config show -p cpu --set tracking.iters=50 > my.yaml

      cpslam config show -c my.yaml --set run.device=cuda
    """
    import yaml

    from cpslam.common.config import config_to_dict

    cfg = config_or_exit(preset, config_file, sets, device, seed)
    typer.echo(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), nl=False)


def presets() -> None:
    """List the presets and what each changes relative to the defaults.

    Examples:

      cpslam config presets

      cpslam config presets > presets.yaml
    """
    from cpslam.common.config import available_presets, preset_text

    for name in available_presets():
        typer.echo(f"# --- {name} ---")
        typer.echo(preset_text(name).rstrip() or "# (the defaults)")


ConnectOpt = Annotated[
    list[str] | None,
    typer.Option("--connect", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447 "
                 "(repeatable; overrides transport.connect)."),
]
SessionOpt = Annotated[
    str | None,
    typer.Option("--session", help="Session name shared by the server and its agents "
                 "(overrides transport.session)."),
]


def transport_sets(session: str | None = None, listen: list[str] | None = None,
                   connect: list[str] | None = None) -> list[str]:
    """`--set` items for the transport flags the daemons share (empty ones are left out)."""
    out = []
    if session is not None:
        out.append(f"transport.session={session}")
    if listen:
        out.append("transport.listen=" + ",".join(listen))
    if connect:
        out.append("transport.connect=" + ",".join(connect))
    return out
