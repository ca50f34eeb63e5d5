"""The hand-written package list in pyproject.toml must cover every source folder; every
module keeps the dependency direction; every command has help with examples."""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

from typer.testing import CliRunner

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
TOP = {"cpslam": "cpslam", "agent": "cpslam.agent", "server": "cpslam.server",
       "common": "cpslam.common", "protocol": "cpslam.protocol", "cpslam/tools": "cpslam.tools"}


def _declared() -> set[str]:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return set(data["tool"]["setuptools"]["packages"])


def test_every_package_folder_is_declared() -> None:
    found = set()
    for folder, name in TOP.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            found.add(".".join([name, *rel.parts]))
    missing = found - _declared()
    assert not missing, f"add to [tool.setuptools] packages in pyproject.toml: {sorted(missing)}"


def test_declared_packages_exist() -> None:
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"]
    for name in _declared():
        # the longest mapped prefix decides the folder: cpslam.agent.x is agent/x, while
        # cpslam.tools.x (unmapped) is cpslam/tools/x
        prefix = max((p for p in package_dir if name == p or name.startswith(p + ".")), key=len)
        folder = ROOT.joinpath(package_dir[prefix], *name[len(prefix):].split(".")[1:])
        assert (folder / "__init__.py").is_file(), f"{name}: no {folder}/__init__.py"


def test_cli_help_and_version() -> None:
    from cpslam import __version__
    from cpslam.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("dataset", "eval"):
        assert command in result.output
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output
    commands = (["dataset"], ["dataset", "synth"], ["dataset", "info"], ["eval", "ate"],
                ["eval", "recon"], ["config", "show"])
    for sub in (c + ["--help"] for c in commands):
        result = runner.invoke(app, sub)
        assert result.exit_code == 0, (sub, result.output)


def _scripts():
    from cpslam.agent_cli import app as agent_app
    from cpslam.cli import app
    from cpslam.server.cli import app as server_app

    return {"cpslam": app, "cpslam-agent": agent_app, "cpslam-server": server_app}


def _leaf_commands(command, path: list[str]):
    """(words after the script name, click command) of every runnable command."""
    subs = getattr(command, "commands", None)
    if not subs:
        yield path, command
        return
    for name, sub in sorted(subs.items()):
        yield from _leaf_commands(sub, [*path, name])


def test_every_command_help_has_examples() -> None:
    # README: "Every command has --help with examples". Found by walking the command tree, so
    # a new command is held to it without being listed here.
    import typer

    runner = CliRunner()
    seen = []
    for script, app in _scripts().items():
        for words, _ in _leaf_commands(typer.main.get_command(app), []):
            result = runner.invoke(app, [*words, "--help"])
            assert result.exit_code == 0, (script, words, result.output)
            full = " ".join([script, *words])
            lines = [line.strip(" │") for line in result.output.splitlines()]
            assert "Example" in result.output and any(
                line.startswith(full + " ") or line == full for line in lines
            ), f"`{full} --help` shows no example line starting with `{full}`"
            seen.append(full)
    assert {"cpslam eval ate", "cpslam eval recon", "cpslam config presets"} <= set(seen)


def test_help_texts_hold_no_rich_markup() -> None:
    # Typer renders help as rich markup: "[s]" or "[default]" in a help text vanishes.
    import typer
    from rich.text import Text

    for script, app in _scripts().items():
        for words, command in _leaf_commands(typer.main.get_command(app), []):
            texts = [command.help or ""] + [getattr(p, "help", None) or "" for p in command.params]
            for text in texts:
                assert Text.from_markup(text).plain == text, (script, words, text)


def test_test_module_names_are_unique() -> None:
    # The test folders are not packages (pytest's default "prepend" import mode): two test
    # files with one basename make collection fail with "import file mismatch".
    seen: dict[str, Path] = {}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        clash = seen.setdefault(path.name, path)
        assert clash == path or path.name == "conftest.py", \
            f"{path.relative_to(ROOT)} and {clash.relative_to(ROOT)} share a module name"


# docs/architecture.md: protocol <- common <- agent, server <- tools; agent and server never
# import each other, and only the umbrella `cpslam/` (cli, demo, run) may import both. The
# offline tools (`cpslam/tools/`) may import the runtime but nothing of the runtime imports
# them, and they never import the umbrella. What each folder may import of cpslam (a name or
# its submodules):
ALLOWED = {
    "protocol": ("cpslam.protocol",),
    "common": ("cpslam.protocol", "cpslam.common"),
    "agent": ("cpslam.protocol", "cpslam.common", "cpslam.agent"),
    "server": ("cpslam.protocol", "cpslam.common", "cpslam.server"),
    "cpslam/tools": ("cpslam.protocol", "cpslam.common", "cpslam.agent", "cpslam.server",
                     "cpslam.tools"),
}
# The wire contract runs without the heavy runtime (docs/protocol.md, architecture.md).
FORBIDDEN_LIBRARIES = {"protocol": ("torch", "zenoh")}


def _imported(path: Path, package: str) -> Iterator[tuple[int, str]]:
    """(line, absolute module name) of every import in `path`, in functions and
    TYPE_CHECKING blocks too; `from cpslam import x` counts as cpslam.x."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            module = _from_module(node, package)
            if module == "cpslam":
                for alias in node.names:
                    yield node.lineno, f"cpslam.{alias.name}"
            else:
                yield node.lineno, module


def _from_module(node: ast.ImportFrom, package: str) -> str:
    """The absolute module of a `from ... import` in `package`."""
    module = node.module or ""
    if node.level:  # relative to the module's own package
        parts = package.split(".")
        module = ".".join([*parts[: len(parts) - node.level + 1], *filter(None, [module])])
    return module


def _violations(root: Path, folder: str) -> list[str]:
    allowed = ALLOWED[folder]
    banned = FORBIDDEN_LIBRARIES.get(folder, ())
    out = []
    for path in sorted((root / folder).rglob("*.py")):
        rel = path.relative_to(root / folder)
        package = ".".join([TOP[folder], *rel.parent.parts])  # an __init__'s is its own
        for line, name in _imported(path, package):
            top = name.split(".")[0]
            ours = top == "cpslam"
            if (ours and not any(name == a or name.startswith(a + ".") for a in allowed)) or (
                    top in banned):
                out.append(f"{folder}/{rel}:{line} imports {name}")
    return out


def test_layers_import_only_downwards() -> None:
    bad = [v for folder in ALLOWED for v in _violations(ROOT, folder)]
    assert not bad, "dependency direction broken (docs/architecture.md):\n" + "\n".join(bad)


def test_layer_check_sees_every_kind_of_import(tmp_path: Path) -> None:
    (tmp_path / "agent" / "sub").mkdir(parents=True)
    (tmp_path / "protocol").mkdir()
    (tmp_path / "agent" / "sub" / "mod.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "from cpslam.common.bus import Bus\n"
        "from cpslam import protocol\n"
        "from .. import node\n"
        "if TYPE_CHECKING:\n    from cpslam.server.backend import Backend\n"
        "def f():\n    import cpslam.demo\n    from cpslam import server\n")
    (tmp_path / "protocol" / "codec.py").write_text("import torch.nn\nimport numpy\n")
    assert _violations(tmp_path, "agent") == [
        "agent/sub/mod.py:6 imports cpslam.server.backend",
        "agent/sub/mod.py:8 imports cpslam.demo",
        "agent/sub/mod.py:9 imports cpslam.server",
    ]
    assert _violations(tmp_path, "protocol") == ["protocol/codec.py:1 imports torch.nn"]


# The back end orchestrates: the modules it drives (loops, groups, federation, refinement,
# result, ...) get their inputs handed in, so only the daemon that owns a back end imports it
# and no import circle through backend.py can form.
# The daemon, and the back end's own parts split out of it for size (they read it whole).
BACKEND_OWNERS = {"backend.py", "node.py", "final.py", "state.py"}


def _imports_backend(path: Path, package: str) -> list[int]:
    lines = [line for line, name in _imported(path, package)
             if name == "cpslam.server.backend" or name.startswith("cpslam.server.backend.")]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):  # from cpslam.server import …
        if (isinstance(node, ast.ImportFrom) and _from_module(node, package) == "cpslam.server"
                and any(alias.name == "backend" for alias in node.names)):
            lines.append(node.lineno)
    return sorted(lines)


def test_only_the_daemon_imports_the_backend() -> None:
    bad = []
    for path in sorted((ROOT / "server").rglob("*.py")):
        rel = path.relative_to(ROOT / "server")
        if rel.as_posix() in BACKEND_OWNERS:
            continue
        package = ".".join(["cpslam.server", *rel.parent.parts])
        bad += [f"server/{rel.as_posix()}:{line}" for line in _imports_backend(path, package)]
    assert not bad, "imports cpslam.server.backend (hand the data in instead): " + ", ".join(bad)


def test_backend_import_check_sees_every_kind_of_import(tmp_path: Path) -> None:
    mod = tmp_path / "mod.py"
    mod.write_text("from typing import TYPE_CHECKING\n"
                   "if TYPE_CHECKING:\n    from cpslam.server.backend import Backend\n"
                   "from .. import backend\n"
                   "def f():\n    from cpslam.server import backend\n")
    assert _imports_backend(mod, "cpslam.server.loops") == [3, 4, 6]


def test_runtime_never_imports_the_tools(tmp_path: Path) -> None:
    (tmp_path / "common").mkdir()
    (tmp_path / "server").mkdir()
    (tmp_path / "cpslam" / "tools" / "eval").mkdir(parents=True)
    (tmp_path / "common" / "io.py").write_text(
        "from cpslam.tools.synth import generate\nfrom cpslam import tools\n")
    (tmp_path / "server" / "export.py").write_text(
        "def f():\n    from cpslam.tools.mesh import tsdf_mesh\n")
    (tmp_path / "cpslam" / "tools" / "eval" / "run.py").write_text(
        "from cpslam.server.node import ServerNode\nfrom cpslam.agent import node\n"
        "from cpslam.common.geometry import invert\nfrom ..mesh import read_mesh\n"
        "from cpslam.demo import demo\n")
    assert _violations(tmp_path, "common") == [
        "common/io.py:1 imports cpslam.tools.synth", "common/io.py:2 imports cpslam.tools"]
    assert _violations(tmp_path, "server") == ["server/export.py:2 imports cpslam.tools.mesh"]
    assert _violations(tmp_path, "cpslam/tools") == [
        "cpslam/tools/eval/run.py:5 imports cpslam.demo"]


def test_only_the_viewer_imports_rerun() -> None:
    """rerun-sdk is the optional `viz` extra: nothing outside cpslam/tools/view imports it, and
    the daemons' and the umbrella's entry points load without pulling it in."""
    import subprocess

    viewer = ROOT / "cpslam" / "tools" / "view"
    bad = []
    for folder in ("protocol", "common", "agent", "server", "cpslam"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if viewer in path.parents:
                continue
            bad += [f"{path.relative_to(ROOT)}:{line}" for line, name in
                    _imported(path, TOP.get(folder, "cpslam"))
                    if name.split(".")[0] in ("rerun", "rerun_bindings")]
    assert not bad, "imports rerun outside cpslam/tools/view: " + ", ".join(bad)
    code = ("import sys, cpslam.agent_cli, cpslam.server.cli, cpslam.cli, cpslam.demo; "
            "print(sorted(m for m in sys.modules if m.split('.')[0].startswith('rerun')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.strip() == "[]", done.stdout
