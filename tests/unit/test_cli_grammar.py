"""One command-line grammar across `cpslam`, `cpslam-agent` and `cpslam-server` (docs/cli.md):
a flag name means the same everywhere, -v/-q/--version work after any subcommand, exit codes
and the overwrite rule are shared. The walk over every command keeps the grammar from drifting
when a command or option is added."""

from __future__ import annotations

import typing
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.cli import App, ExitCode, verbosity

runner = CliRunner()


def _scripts() -> dict[str, typer.Typer]:
    from cpslam.agent_cli import app as agent_app
    from cpslam.cli import app
    from cpslam.server.cli import app as server_app

    return {"cpslam": app, "cpslam-agent": agent_app, "cpslam-server": server_app}


def _commands(command, path: list[str]):
    """(words, click command) of every command and group, the root included."""
    yield path, command
    for name, sub in sorted(getattr(command, "commands", {}).items()):
        yield from _commands(sub, [*path, name])


def _value_type(param) -> str:
    """The type of one value of an option (a repeatable option's element type)."""
    annotation = param.type_descriptor.annotation
    if typing.get_origin(annotation) is list:
        annotation = typing.get_args(annotation)[0]
    return getattr(annotation, "__name__", str(annotation))


def _options() -> dict[str, list[tuple[str, tuple]]]:
    """Long option name -> [(command, (all its names, is_flag, count, value type))]."""
    table = defaultdict(list)
    for script, app in _scripts().items():
        for words, command in _commands(typer.main.get_command(app), [script]):
            for p in command.params:
                if p.param_type_name != "option":
                    continue
                name = next(o for o in p.opts if o.startswith("--"))
                shape = (tuple(sorted(p.opts + p.secondary_opts)), p.is_flag, p.count,
                         _value_type(p))
                table[name].append((" ".join(words), shape, p.help or ""))
    return table


def test_every_flag_name_has_one_shape_everywhere() -> None:
    table = _options()
    for name, uses in table.items():
        shapes = {shape for _, shape, _ in uses}
        assert len(shapes) == 1, f"{name} differs between commands: {uses}"
    shorts = defaultdict(set)
    for name, uses in table.items():
        for short in (o for o in uses[0][1][0] if not o.startswith("--")):
            shorts[short].add(name)
    assert all(len(names) == 1 for names in shorts.values()), shorts


def test_shared_flags_mean_what_docs_cli_says() -> None:
    table = _options()

    def shape(name: str) -> tuple:
        return table[name][0][1]

    assert shape("--json") == (("--json",), True, False, "bool")
    assert shape("--overwrite") == (("--overwrite",), True, False, "bool")
    assert shape("--out") == (("--out", "-o"), False, False, "Path")
    assert shape("--frames")[3] == "str"  # a slice START:STOP[:STEP]; counts are --num-frames
    assert shape("--num-frames")[3] == "int"
    assert all("run.seed" in help for _, _, help in table["--seed"])
    assert {"cpslam dataset synth", "cpslam demo"} <= {c for c, _, _ in table["--scene-seed"]}
    every = {c for script, app in _scripts().items()
             for c in (" ".join(w) for w, _ in _commands(typer.main.get_command(app), [script]))}
    for name in ("--verbose", "--quiet", "--version"):
        assert {c for c, _, _ in table[name]} == every, name


def test_docs_cli_lists_every_shared_flag() -> None:
    text = (Path(__file__).resolve().parents[2] / "docs" / "cli.md").read_text()
    shared = [name for name, uses in _options().items() if len({c for c, _, _ in uses}) > 1]
    missing = [name for name in shared if f"`{name}" not in text]
    assert not missing, f"docs/cli.md does not list {missing}"


@pytest.mark.parametrize("script", ["cpslam", "cpslam-agent", "cpslam-server"])
def test_version_on_every_entry_point(script: str) -> None:
    from cpslam import __version__

    result = runner.invoke(_scripts()[script], ["--version"])
    assert result.exit_code == 0 and __version__ in result.output


def test_verbosity_counts_flags_before_and_after_the_subcommand() -> None:
    seen = []
    app = App()

    @app.callback()
    def _root() -> None:
        pass

    @app.command()
    def probe(ctx: typer.Context) -> None:
        seen.append(verbosity(ctx))

    for args, expected in ((["probe"], 0), (["-v", "probe", "-v"], 2),
                           (["probe", "-vv", "-q"], 1), (["-q", "probe"], -1)):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        assert seen.pop() == expected, args


def test_v_and_q_after_the_subcommand_on_every_entry_point(tmp_path: Path) -> None:
    scripts = _scripts()
    assert runner.invoke(scripts["cpslam"], ["config", "show", "-v", "-q"]).exit_code == 0
    assert runner.invoke(scripts["cpslam"], ["config", "presets", "--quiet"]).exit_code == 0
    for script, args in (("cpslam-agent", ["--seq", str(tmp_path), "--standalone"]),
                         ("cpslam-server", [])):
        result = runner.invoke(scripts[script], [*args, "--preset", "nonesuch", "-q", "-v"])
        assert result.exit_code == ExitCode.USAGE and "nonesuch" in result.output, script


def test_status_without_a_server_exits_no_server() -> None:
    from cpslam.demo import free_port

    result = runner.invoke(_scripts()["cpslam"], [
        "status", "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "0.5"])
    assert result.exit_code == ExitCode.NO_SERVER == 3, result.output


@pytest.mark.slow
def test_agent_without_a_server_exits_no_server_too(tmp_path: Path) -> None:
    from cpslam.demo import free_port, scene_data

    nobody = f"tcp/127.0.0.1:{free_port()}"
    seq = scene_data(tmp_path, "room", 1, 3, 16, 12, seed=0, show_progress=False)[0]
    result = runner.invoke(_scripts()["cpslam-agent"], [
        "--seq", str(seq), "--preset", "tiny", "--connect", nobody, "--wait-timeout", "0.5",
        "--no-progress", "--out", str(tmp_path / "run"), "-q"])
    assert result.exit_code == ExitCode.NO_SERVER, result.output


def test_existing_outputs_are_replaced_only_with_overwrite(tmp_path: Path) -> None:
    from cpslam.common.trajectory import write_tum

    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, 0, 3] = np.arange(5) * 0.1
    write_tum(tmp_path / "gt.tum", np.arange(5.0), poses)
    out = tmp_path / "ate.json"
    out.write_text("mine")
    args = ["eval", "ate", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / "gt.tum"),
            "--out", str(out)]
    result = runner.invoke(_scripts()["cpslam"], args)
    assert result.exit_code == ExitCode.USAGE and "--overwrite" in result.output
    assert out.read_text() == "mine"
    result = runner.invoke(_scripts()["cpslam"], [*args, "--overwrite", "--json"])
    assert result.exit_code == 0, result.output
    assert '"n_pairs": 5' in result.output and '"n_pairs": 5' in out.read_text()
