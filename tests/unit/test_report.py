"""The end-of-run report on hand-made run folders: numbers, table, plots, missing mesh,
ground truth found where the agents recorded it, `--gt` values, a lone agent's folder."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from cpslam.common.geometry import compose
from cpslam.common.trajectory import write_tum
from cpslam.tools.report import build_report, main_group
from cpslam.tools.report_table import print_report
from cpslam.tools.runfolder import parse_gt_options, recorded_sequences


def _circle(n: int, phase: float) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    angle = phase + np.linspace(0, np.pi, n)
    poses[:, 0, 3], poses[:, 1, 3] = 2 * np.cos(angle), 2 * np.sin(angle)
    poses[:, 2, 3] = 1.0
    return poses


def _offset(x: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


@pytest.fixture
def run(tmp_path: Path) -> tuple[Path, dict[str, Path]]:
    """Two agents merged into group 0 at 12.5 s; agent 1's global poses are 3 cm off."""
    run, stamps = tmp_path / "run", np.arange(50) / 10.0
    rng = np.random.default_rng(0)
    seqs = {}
    T_group_world = _offset(0.7, 0.3)  # the group frame is not the ground truth's
    for a, phase in (("0", 0.0), ("1", 2.0)):
        gt = _circle(50, phase)
        seqs[a] = tmp_path / f"gt_{a}.tum"
        write_tum(seqs[a], stamps, gt)
        glob = np.stack([compose(T_group_world, T) for T in gt])
        if a == "1":
            glob[:, 1, 3] += 0.03
        glob[:, :3, 3] += rng.normal(0, 1e-3, (50, 3))
        local = np.stack([compose(np.linalg.inv(gt[0]), T) for T in gt])
        write_tum(run / "trajectories" / f"agent_{a}_global.tum", stamps, glob)
        write_tum(run / "trajectories" / f"agent_{a}_local.tum", stamps, local)
        (run / f"agent_{a}").mkdir(parents=True)
        (run / f"agent_{a}" / "metrics.json").write_text(json.dumps({
            "points": 1000 + int(a), "peak_cpu_memory_mb": 600.0 + int(a), "bus": {"sent": {
                f"cpslam/demo/agent/{a}/keyframe": {"messages": 3, "bytes": 2_000_000},
                f"cpslam/demo/agent/{a}/frames": {"messages": 5, "bytes": 500_000}}}}))
    loops = [{"agent_a": "0", "agent_b": "0", "accepted": True},
             {"agent_a": "0", "agent_b": "1", "accepted": True},
             {"agent_a": "1", "agent_b": "0", "accepted": False}]
    metrics = {
        "groups": [{"group_id": "0", "members": ["0", "1"]}],
        "agents": {a: {"group": "0", "merged": True, "bytes": 1} for a in seqs},
        "loops": {"found": 5, "accepted": 2, "rejected": 1, "list": loops},
        "merges": [{"time": 12.5, "group": "0", "members": ["0", "1"]}],
        "refinement": [{"group": "0", "points": 1800}],
        "bus": {"per_agent": {a: {
            "from_agent_bytes": 7, "to_agent_bytes": 300_000,
            "from_agent": {"keyframe": {"messages": 1, "bytes": 7, "bytes_per_s": 0.7}},
            "to_agent": {"ack": {"messages": 2, "bytes": 100_000, "bytes_per_s": 10_000.0},
                         "group_decoder": {"messages": 1, "bytes": 200_000,
                                           "bytes_per_s": 20_000.0}}} for a in seqs},
            "per_group": {"0": {"messages": 1, "bytes": 200_000, "bytes_per_s": 20_000.0}}},
        "process": {"peak_rss_mb": 712.4, "uptime_s": 10.0},
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    return run, seqs


def test_report_numbers(run: tuple[Path, dict[str, Path]]) -> None:
    folder, seqs = run
    report = build_report(folder, seqs, mesh=True)
    a0, a1, total = report["agents"]["0"], report["agents"]["1"], report["all"]
    assert a0["frames"] == a1["frames"] == 50
    assert a0["local_ate_m"] < 0.01 and a1["local_ate_m"] < 0.01
    # One alignment for both: agent 1's 3 cm offset shows in both, shared out.
    assert 0.005 < a0["global_ate_m"] < 0.03 and 0.005 < a1["global_ate_m"] < 0.03
    assert total["joint_ate_m"] == pytest.approx(0.015, abs=0.005)
    assert a0["merged_at_s"] == a1["merged_at_s"] == 12.5 and a0["group"] == "0"
    assert (a0["loops_accepted"], a0["loops_verified"]) == (2, 3)
    assert (a1["loops_accepted"], a1["loops_verified"]) == (1, 2)
    assert a0["points"] == 1000 and total["fused_points"] == 1800
    assert a0["sent_bytes"] == 2_500_000 and total["sent_bytes"] == 5_000_000
    assert total["received_bytes"] == 600_000
    assert (total["loops_found"], total["loops_accepted"]) == (5, 2)
    for plot in report["plots"]:
        assert Path(plot).read_bytes()[:4] == b"\x89PNG"
    assert "fused_map.pt" in report["mesh"]["skipped"]
    assert json.loads((folder / "report.json").read_text())["all"]["groups"] == 1
    traffic = report["traffic"]
    assert traffic["agents"]["1"]["to_agent"]["group_decoder"]["bytes_per_s"] == 20_000.0
    assert traffic["agents"]["0"]["from_agent"]["keyframe"]["bytes"] == 7
    assert traffic["groups"]["0"]["bytes"] == 200_000 and traffic["seconds"] == 10.0
    memory = report["memory_mb"]
    assert memory["server"] == 712.4 and memory["agent_0"] == 600.0
    assert memory["agent_1"] == 601.0 and memory["report"] > 10  # this process

    out = io.StringIO()
    print_report(report, Console(file=out, width=100))
    text = out.getvalue()
    assert "ATE glob" in text and "12.5" in text and "2.50" in text and "1800" in text
    assert "mesh skipped" in text
    assert "traffic per agent" in text and "group_decoder" in text and "20.00" in text
    assert "peak memory (MB): server 712, agent 0 600, agent 1 601, report" in text


def test_report_without_ground_truth_or_agent_bus(run: tuple[Path, dict[str, Path]]) -> None:
    folder, _ = run
    for a in ("0", "1"):
        (folder / f"agent_{a}" / "metrics.json").unlink()
    report = build_report(folder, None, mesh=False)
    assert "local_ate_m" not in report["agents"]["0"] and "plots" not in report
    assert report["agents"]["0"]["sent_bytes"] == 7  # what the server received from it
    assert report["agents"]["0"]["points"] is None
    assert any("no ATE" in n for n in report["notes"])
    out = io.StringIO()
    print_report(report, Console(file=out, width=100))
    assert " - " in out.getvalue()
    assert report["memory_mb"]["agent_0"] is None and "agent 0 -" in out.getvalue()


def test_report_needs_the_server_metrics(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="metrics.json"):
        build_report(tmp_path)


def test_main_group_is_the_largest() -> None:
    metrics = {"groups": [{"group_id": "a", "members": ["0"]},
                          {"group_id": "b", "members": ["1", "2"]},
                          {"group_id": "c", "members": ["3", "4"]}],
               "refinement": [{"group": "b", "points": 10}, {"group": "c", "points": 20}]}
    assert main_group(metrics) == "c"
    assert main_group({}) is None


def test_ground_truth_is_found_where_the_agents_recorded_it(
        run: tuple[Path, dict[str, Path]], tmp_path: Path) -> None:
    folder, seqs = run
    for a, path in seqs.items():  # as write_agent_outputs records the sequence
        metrics_path = folder / f"agent_{a}" / "metrics.json"
        metrics = json.loads(metrics_path.read_text())
        metrics["sequence"] = {"path": str(path), "format": "tum", "frames": 50}
        metrics_path.write_text(json.dumps(metrics))
    assert recorded_sequences(folder) == seqs
    report = build_report(folder, mesh=False)
    assert report["ground_truth"] == {a: str(p) for a, p in seqs.items()}
    assert report["all"]["joint_ate_m"] == pytest.approx(0.015, abs=0.005)
    # A recorded sequence that is gone is dropped; demo.json is read as well.
    seqs["1"].unlink()
    (folder / "demo.json").write_text(json.dumps({"sequences": {"7": str(seqs["0"])}}))
    assert recorded_sequences(folder) == {"0": seqs["0"], "7": seqs["0"]}


def test_gt_options_name_agents_or_take_them_in_order(tmp_path: Path) -> None:
    assert parse_gt_options(["a", "1=b"], ["0", "1"]) == {"0": Path("a"), "1": Path("b")}
    assert parse_gt_options(["robot-2=x"], ["robot-2"]) == {"robot-2": Path("x")}
    with pytest.raises(ValueError, match="agent '5' is not in this run"):
        parse_gt_options(["5=x"], ["0", "1"])
    with pytest.raises(ValueError, match="more ground truths than the run's 1 agent"):
        parse_gt_options(["a", "b"], ["0"])
    odd = tmp_path / "x=y"  # an existing path holding "=" is a path
    odd.mkdir()
    assert parse_gt_options([str(odd)], ["0"]) == {"0": odd}


def test_lone_agent_folder_has_no_server_part(run: tuple[Path, dict[str, Path]]) -> None:
    folder, seqs = run
    lone = folder.parent / "lone"
    (lone / "agent_0").mkdir(parents=True)
    (lone / "agent_0" / "trajectory.tum").write_text(
        (folder / "trajectories" / "agent_0_local.tum").read_text())
    report = build_report(lone, {"0": seqs["0"]}, mesh=False)
    assert report["kind"] == "agent" and report["agents"]["0"]["frames"] == 50
    assert report["agents"]["0"]["local_ate_m"] < 0.01 and "server" not in report["memory_mb"]
    out = io.StringIO()
    print_report(report, Console(file=out, width=100))
    assert "one agent, no server" in out.getvalue()


def test_unfinalised_server_folder_is_refused(run: tuple[Path, dict[str, Path]]) -> None:
    folder, _ = run
    (folder / "metrics.json").unlink()
    (folder / "server_state.pt").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match="has not finalised"):
        build_report(folder, mesh=False)
