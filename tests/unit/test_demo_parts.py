"""`cpslam demo` pieces that need no daemons: supervisor, frame choice, folders, scene cache."""

from __future__ import annotations

import socket
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cpslam.cli import app
from cpslam.demo import (
    MARKER,
    frame_slice,
    free_port,
    prepare_run_dir,
    scene_data,
)
from cpslam.supervisor import ChildFailed, Supervisor

PY = sys.executable


def _wait_exit(sup: Supervisor, name: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while sup.running(name) and time.monotonic() < deadline:
        time.sleep(0.05)


def test_a_child_that_fails_is_named_with_its_log(tmp_path: Path) -> None:
    with Supervisor(tmp_path / "logs") as sup:
        sup.start("sleeper", [PY, "-c", "import time; time.sleep(60)"])
        sup.start("agent_7", [PY, "-c", "print('loading frames'); raise SystemExit(1)"])
        _wait_exit(sup, "agent_7")
        with pytest.raises(ChildFailed) as info:
            sup.check()
    err = info.value
    assert err.name == "agent_7" and err.code == 1
    assert err.log == tmp_path / "logs" / "agent_7.log"
    assert "agent_7 exited with code 1" in str(err) and str(err.log) in str(err)
    assert "loading frames" in str(err)  # the tail of its log
    # Leaving the supervisor stopped the others.
    assert not sup.running("sleeper")


def test_normal_exit_is_fine_but_a_server_must_not_exit(tmp_path: Path) -> None:
    with Supervisor(tmp_path) as sup:
        sup.start("agent_0", [PY, "-c", "pass"])
        _wait_exit(sup, "agent_0")
        sup.check()  # exit 0 of an agent is its normal end
        sup.start("server", [PY, "-c", "pass"], may_exit=False)
        _wait_exit(sup, "server")
        with pytest.raises(ChildFailed, match="server exited with code 0"):
            sup.check()


def test_close_forwards_one_sigint_then_kills(tmp_path: Path) -> None:
    graceful = ("import signal, sys, time\n"
                "def stop(*_):\n    print('finalising', flush=True); sys.exit(0)\n"
                "signal.signal(signal.SIGINT, stop)\nprint('ready', flush=True)\n"
                "time.sleep(60)\n")
    stubborn = ("import signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                "print('ready', flush=True)\ntime.sleep(60)\n")
    sup = Supervisor(tmp_path)
    server = sup.start("server", [PY, "-c", graceful])
    agent = sup.start("agent_0", [PY, "-c", stubborn])
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and not all(
            "ready" in c.log.read_text() for c in (server, agent)):
        time.sleep(0.05)
    t0 = time.monotonic()
    sup.close(grace_s=1.0)
    assert time.monotonic() - t0 < 10
    assert server.proc.returncode == 0 and "finalising" in server.log.read_text()
    assert agent.proc.returncode == -9  # ignored SIGINT: killed after the grace period


def test_frame_slice_spreads_frames_over_the_walk() -> None:
    assert frame_slice(300, 100) == "0:300:3"
    assert frame_slice(300, 30) == "0:300:10"
    assert frame_slice(300, 120) == "0:240:2"
    assert frame_slice(300, 300) == "0:300:1"
    assert frame_slice(400, 400) == "0:400:1"


def test_free_port_can_be_bound() -> None:
    port = free_port()
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", port))


def test_run_folder_replaces_only_an_earlier_demo(tmp_path: Path) -> None:
    run = tmp_path / "demo"
    prepare_run_dir(run)
    (run / MARKER).write_text("{}")
    (run / "metrics.json").write_text("{}")
    with pytest.raises(FileExistsError, match="--overwrite"):
        prepare_run_dir(run)
    assert (run / "metrics.json").is_file()
    prepare_run_dir(run, overwrite=True)
    assert run.is_dir() and not any(run.iterdir())
    (run / "precious.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not an earlier demo"):
        prepare_run_dir(run, overwrite=True)
    assert (run / "precious.txt").is_file()


def test_scene_is_generated_once_and_cached(tmp_path: Path) -> None:
    first = scene_data(tmp_path, "room", 1, 3, 16, 12, seed=0, show_progress=False)
    assert first == [tmp_path / "room-1x3-16x12-s0" / "agent_0"]
    stamp = (first[0].parent / "scene.json").stat().st_mtime_ns
    assert scene_data(tmp_path, "room", 1, 3, 16, 12, seed=0, show_progress=False) == first
    assert (first[0].parent / "scene.json").stat().st_mtime_ns == stamp


def test_cli_refuses_bad_arguments_before_any_work(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["demo", "--scene", "castle", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "apartment or room" in result.output
    result = runner.invoke(app, ["demo", "--set", "nonsense.key=1", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("x")
    result = runner.invoke(app, ["demo", "--out", str(tmp_path / "busy"),
                                 "--data-dir", str(tmp_path / "data")])
    assert result.exit_code == 2 and "not an earlier demo" in result.output
    assert not (tmp_path / "data").exists()


def test_report_step_shows_traffic_and_memory_of_every_process(tmp_path: Path,
                                                               capsys) -> None:
    import json

    import numpy as np

    from cpslam.common.trajectory import write_tum
    from cpslam.demo import _report

    run = tmp_path / "demo"
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    write_tum(run / "trajectories" / "agent_0_global.tum", np.arange(3.0), poses)
    (run / "agent_0").mkdir()
    (run / "agent_0" / "metrics.json").write_text(json.dumps({"peak_cpu_memory_mb": 321.0}))
    cell = {"messages": 4, "bytes": 4_000_000, "bytes_per_s": 2_000_000.0,
            "bytes_per_sensor_s": 40_000.0}
    (run / "metrics.json").write_text(json.dumps({
        "bus": {"per_agent": {"0": {"from_agent": {"submap": cell}, "to_agent": {},
                                    "from_agent_bytes": 4_000_000, "to_agent_bytes": 0}}},
        "process": {"peak_rss_mb": 654.0, "uptime_s": 2.0}}))
    info = {"agents": 1, "preset": "tiny", "frames": 3, "wall_s": 1.0,
            "sequences": {"0": str(tmp_path / "no-ground-truth")}}
    _report(run, info, mesh=False, show=False)
    marker = json.loads((run / MARKER).read_text())
    memory = marker["memory_mb"]
    assert memory["server"] == 654.0 and memory["agent_0"] == 321.0 and memory["demo"] > 10
    assert json.loads((run / "report.json").read_text())["memory_mb"] == memory
    out = capsys.readouterr().out
    assert "submap" in out and "2000.00" in out and "4.00" in out  # kB/s and MB
    assert "kB/sensor-s" in out and "40.00" in out
    assert "peak memory (MB): server 654, agent 0 321, demo" in out
