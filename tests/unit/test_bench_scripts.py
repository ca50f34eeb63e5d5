"""The bench scripts stay runnable: each parses its arguments and prints its usage, and the
odometry bench's seed summary is what its table reads."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if 'if __name__ == "__main__"' in p.read_text())


def _bench_module(name: str):
    sys.path.insert(0, str(BENCH))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(BENCH))


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_script_prints_its_usage(script: str) -> None:
    done = subprocess.run([sys.executable, str(BENCH / script), "--help"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "usage:" in done.stdout


def test_odometry_bench_summarises_runs(capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench_module("odometry")
    base = {"kind": "room", "threads": 1, "capability": "default", "seed": 0,
            "ate_se3_cm": 0.5, "rpe1_mm": 1.0, "rpe1_deg": 0.1, "s_per_frame": 1.0,
            "tracking_s_per_frame": 0.5, "mapping_s_per_call": 3.0,
            "s_per_frame_after_first": 0.9}
    runs = [{**base, "sequence": "room-0", "ate_origin_cm": 0.8, "max_error_cm": 2.0,
             "events": {"suspect": 2, "recovered": 2, "lost": 0}},
            {**base, "sequence": "room-0", "threads": 2, "ate_origin_cm": 1.2,
             "max_error_cm": 12.0, "events": {"suspect": 1, "recovered": 0, "lost": 1}},
            {**base, "sequence": "kitchen", "kind": "real", "ate_se3_cm": 2.0,
             "ate_se3_pieces_cm": 1.5, "max_error_cm": 5.0},
            {"sequence": "kitchen", "threads": 2, "capability": "avx2", "seed": 0,
             "error": "boom"}]
    open3d = {"kitchen": {"320x240": {"ate_se3_cm": 2.5, "ate_se3_pieces_cm": 2.0,
                                      "s_per_frame": 0.1},
                          "640x480": {"ate_se3_cm": 4.0, "ate_se3_pieces_cm": 3.0,
                                      "s_per_frame": 0.4}}}
    summary = bench.summarise(runs, open3d)
    room = summary["per_sequence"]["room-0"]
    assert room["mean"] == 1.0 and room["worst"] == 1.2 and room["lost_runs"] == 1
    assert room["events"] == {"suspect": 3, "recovered": 2, "lost": 1}
    kitchen = summary["per_sequence"]["kitchen"]
    assert kitchen["ratio_mean_over_best_open3d"] == 0.8  # against the better Open3D
    assert kitchen["ratio_pieces_mean_over_best_open3d"] == 0.75
    # Time against Open3D at the frames' full size (640x480), not the faster half size.
    assert kitchen["s_per_frame_over_open3d_full"] == 2.5
    assert "s_per_frame_over_open3d_full" not in room  # no Open3D run on it
    assert summary["synthetic"]["runs_over_1cm"] == 1 and summary["failed_runs"] == 1
    bench.print_tables({"runs": runs, "summary": summary, "open3d": open3d})
    out = capsys.readouterr().out
    assert "error" in out and "1 lost track" in out and "s/frame / Open3D full" in out
    text = _bench_module("render_results")._odometry(
        {"runs": runs, "summary": summary, "open3d": open3d, "preset": "cpu", "overrides": []})
    assert "| s/frame over Open3D's at full size |" in text
    assert "| 0.8 / 0.8 | 0.75 | 1.0 | 2.5 |" in text  # the kitchen row
    assert "| 1.0 | - |" in text  # room-0: no Open3D, no ratio


def test_odometry_bench_puts_loop_closure_beside_the_odometry(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Runs with loop closure fill `with_loops` and leave the odometry's fields as they were;
    the results page reads such a report, and an older one without them unchanged."""
    bench = _bench_module("odometry")
    render = _bench_module("render_results")
    base = {"sequence": "room-0", "kind": "room", "threads": 1, "capability": "default",
            "seed": 0, "ate_se3_cm": 0.5, "max_error_cm": 2.0, "s_per_frame": 1.0,
            "tracking_s_per_frame": 0.5, "mapping_s_per_call": 3.0,
            "s_per_frame_after_first": 0.9}
    runs = [{**base, "loops": "off", "ate_origin_cm": 2.0},
            {**base, "loops": "on", "ate_origin_cm": 0.8, "loops_found": 3, "loops_accepted": 2},
            {**base, "loops": "on", "seed": 1, "ate_origin_cm": 1.2, "max_error_cm": 11.0,
             "loops_found": 1, "loops_accepted": 1}]
    summary = bench.summarise(runs, {})
    old = bench.summarise([{k: v for k, v in runs[0].items() if k != "loops"}], {})
    room = summary["per_sequence"]["room-0"]
    assert {k: v for k, v in room.items() if k != "with_loops"} == old["per_sequence"]["room-0"]
    assert room["mean"] == 2.0 and room["runs"] == 1
    assert room["with_loops"] == {"metric": "ate_origin_cm", "runs": 2, "mean": 1.0,
                                  "worst": 1.2, "lost_runs": 1, "loops_found": 4,
                                  "loops_accepted": 3, "s_per_frame": 1.0}
    assert summary["synthetic"] == old["synthetic"]
    assert summary["synthetic_with_loops"]["runs"] == 2
    report = {"runs": runs, "summary": summary, "open3d": {}, "preset": "tiny", "overrides": []}
    bench.print_tables(report)
    assert "loops accepted 3 of 4 found" in capsys.readouterr().out
    text = render._odometry(report)
    assert "| room-0 | origin | 1 | 2.0 | 2.0 | 0 | - | - | - | 1.0 | 1.0 / 1.2 | 3 / 4 |" in text
    assert "runs without loop closure" in text
    plain = render._odometry({**report, "runs": runs[:1], "summary": old})
    assert "with loops" not in plain and "| room-0 | origin | 1 | 2.0 |" in plain


@pytest.mark.parametrize("bench_name", ["odometry", "loop_edges", "gpu_check"])
def test_a_reports_note_follows_its_provenance_whatever_the_bench(tmp_path: Path,
                                                            bench_name: str) -> None:
    render = _bench_module("render_results")
    committed = sorted((BENCH / "results").glob("*.json"))
    report = next(r for r in (json.loads(p.read_text()) for p in committed)
                  if r.get("bench") == bench_name)
    path = tmp_path / "with-note.json"
    path.write_text(json.dumps({**report, "note": "Ran beside the test suite."}))
    section = render.render([path]).split("## with-note\n\n", 1)[1]
    provenance, note, body = section.split("\n\n", 2)
    assert provenance.startswith("`") and note == "Ran beside the test suite."
    assert "Ran beside the test suite." not in body  # rendered once, not again by the bench
    report.pop("note", None)
    path.write_text(json.dumps(report))
    assert "Ran beside" not in render.render([path])


def test_odometry_bench_scenes_alternate_kind_and_noise() -> None:
    specs = _bench_module("odometry_runs").scene_specs(4, 100)
    assert [(s["kind"], s["noise"], s["seed"]) for s in specs] == [
        ("room", False, 100), ("apartment", False, 101), ("room", True, 102),
        ("apartment", True, 103)]
    assert [s["name"] for s in specs][2] == "room-102-noise"


def test_odometry_accuracy_leaves_out_spans_longer_than_the_run() -> None:
    runs = _bench_module("odometry_runs")
    stamps = np.arange(8, dtype=np.float64)
    poses = np.repeat(np.eye(4)[None], 8, axis=0)
    poses[:, 0, 3] = 0.01 * stamps  # 1 cm per frame
    est = poses.copy()
    est[:, 0, 3] *= 1.1  # 1 mm per frame too far

    class Seq:
        timestamps = stamps

        @staticmethod
        def gt_poses():
            return poses

    out = runs.accuracy(Seq(), stamps, est, real=False)
    assert out["rpe1_mm"] == pytest.approx(1.0) and "rpe10_mm" not in out
    assert out["max_error_cm"] == pytest.approx(0.7)  # frame 7: 7.7 cm instead of 7 cm


def test_results_page_is_rendered_from_the_committed_json() -> None:
    render = _bench_module("render_results")
    paths = sorted(render.RESULTS.glob("*.json"))
    assert paths, "bench/results/ holds no result files"
    assert render.DOC.read_text() == render.render(paths), \
        "docs/results.md is stale: python bench/render_results.py"


def test_every_committed_report_is_on_the_results_page() -> None:
    """No bench's figures are left out of docs/results.md for want of a renderer."""
    render = _bench_module("render_results")
    paths = sorted(render.RESULTS.glob("*.json"))
    missing = {p.name for p in paths
               if json.loads(p.read_text()).get("bench") not in render.RENDERERS}
    assert not missing, missing
    page = render.render(paths)
    assert all(f"## {p.stem}\n" in page for p in paths)


def test_stage_profile_and_knob_reports_render_their_tables() -> None:
    render = _bench_module("render_results")
    stage = {"calls_per_frame": 2.0, "ms_per_call": 5.0, "s_per_frame": 0.01,
             "share_phase": 0.25}
    phase = {"s_per_frame": 0.04, "stages": {"search": stage, "decoder_forward": stage}}
    report = {"preset": "cpu", "overrides": ["mapping.iters_first=100"], "threads": 1,
              "frames": 11, "resolution": [240, 320], "track_iters_per_frame": 7.0,
              "map_steps_per_frame": 10.0,
              "first_frame": {"mapping": {"s_per_frame": 12.0}, "total_s_per_frame": 12.5},
              "per_frame": {"tracking": phase, "total_s_per_frame": 0.04}}
    text = render._stage_profile(report)
    assert "frames 1-10 at 320x240: 7.0 LM solves and 10.0 mapping steps" in text
    assert "|  | decoder_forward | 0.010 | 5.0 | 2.0 | 25 % |" in text
    assert "| **tracking** |  | **0.040** |" in text and "**mapping**" not in text
    assert "First frame (the first mapping call): 12.5 CPU s, mapping 12.0." in text
    run = {"ate_se3_cm": 0.6, "max_error_cm": 1.5, "rpe1_mm": 4.2, "rpe1_deg": 0.15,
           "events": {"suspect": 1, "recovered": 1, "lost": 0}, "s_per_frame": 2.0,
           "s_per_frame_after_first": 1.5, "tracking_s_per_frame": 1.0,
           "mapping_s_per_call": 6.0, "first_mapping_s": 30.0}
    text = render._knobs({"runs": {"preset": run, "tracking.iters=5": {"error": "boom"}}})
    assert "| preset | 0.6 | 1.5 | 4.2 / 0.15 | 1 / 1 / 0 | 2.0 | 1.5 | 1.0 | 6.0 | 30.0 |" in text
    assert "| tracking.iters=5 | error |" in text


def test_loop_edges_bench_says_where_the_ground_truth_fits_worse() -> None:
    """Real pairs carry how well the views fit at the ground truth and at the registered
    pose; the summary counts the pairs the registration fits better and the page says so."""
    bench, render = _bench_module("loop_edges"), _bench_module("render_results")
    seq = {"real": True, "size": "320x240", "pairs": 3, "accepted": 3,
           "errors": [[0, 45, 1.0, 0.1, 0.9], [0, 75, 2.0, 0.2, 0.8], [30, 75, 3.0, 0.3, 0.7]],
           "chi2_raw": [1.0, 2.0, 3.0],
           "truth_fit": [[0, 45, 12.0, 11.0, 0.8, 0.9], [0, 75, 17.0, 18.0, 0.8, 0.8],
                         [30, 75, 21.0, 16.0, 0.7, 0.75]]}
    summary = bench.summarise({"kitchen@1": seq}, 1.0)
    assert summary["real@320x240"]["truth_fit"] == {
        "pairs": 3, "registered_fits_better": 2,
        "rmse_mm_median": {"ground_truth": 17.0, "registered": 16.0},
        "color_median": {"ground_truth": 0.8, "registered": 0.8}}
    text = render._loop_edges({"information_scale": 1.0, "summary": summary})
    assert "ground-truth pose in real@320x240: 2 of 3 pairs, point-to-plane RMS median " \
        "16.0 mm registered against 17.0 at the ground truth" in text
    synthetic = bench.summarise({"room@1": {**seq, "real": False, "truth_fit": []}}, 1.0)
    assert "truth_fit" not in synthetic["synthetic@320x240"]


def test_collab_table_reads_a_report() -> None:
    render = _bench_module("render_results")
    edges = {"edges": [{"trans_cm": 1.0}], "trans_cm_median": 1.0, "trans_cm_p90": 2.0,
             "trans_cm_max": 3.0, "rot_deg_median": 0.1, "chi2_gt_median": 5.0, "kept": 1}
    section = {"global_joint_se3_rmse_m": 0.02, "odometry_joint_se3_rmse_m": 0.04,
               "loops": {"accepted": 1, "found": 2}, "loop_edges": edges,
               "false_loop_test": {"false_flagged": 1, "false_loops": 1}}
    text = render._collab({"preset": "cpu", "sets": [], "real_split": section})
    assert "| real split | 2.00 / 4.00 (0.50) | 1 / 2 | 1.0 / 2.0 / 3.0 |" in text


def test_first_call_table_adds_colour_when_the_report_has_it() -> None:
    render = _bench_module("render_results")
    run = {"frame": "kitchen-0", "setting": "a", "overrides": [], "steps": 100,
           "seconds": 9.5, "final_l1_cm": 1.2, "window_l1_cm": [2.0, 1.2]}
    report = {"preset": "cpu", "threads": 2, "window": 50, "runs": [run]}
    old = render._first_call(report)
    assert "| kitchen-0 | a (`preset`) | 100 | 9.5 | 1.2 | 2.0 1.2 |" in old
    assert "colour" not in old
    coloured = render._first_call({**report, "runs": [{**run, "final_color_l1": 0.04}]})
    assert "| kitchen-0 | a (`preset`) | 100 | 9.5 | 1.2 | 2.0 1.2 | 0.04 |" in coloured


def test_odometry_accuracy_over_the_frames_done() -> None:
    """A run stopped by its time budget is scored against as many ground-truth poses."""
    runs = _bench_module("odometry_runs")
    stamps = np.arange(8, dtype=np.float64)
    poses = np.repeat(np.eye(4)[None], 8, axis=0)
    poses[:, 0, 3] = 0.01 * stamps

    class Seq:
        timestamps = stamps

        @staticmethod
        def gt_poses():
            return poses

    est = poses[:5].copy()
    est[4, 0, 3] += 0.02  # the last frame done is 2 cm off
    out = runs.accuracy(Seq(), stamps[:5], est, real=False, frames=5)
    assert out["max_error_cm"] == pytest.approx(2.0)
    assert "rpe10_mm" not in out and out["rpe1_mm"] > 0


def test_gpu_report_rows_runs_failures_and_the_paper() -> None:
    report = _bench_module("gpu_report")
    run = {"sequence": "7scenes-kitchen", "kind": "real", "frames": 40, "frames_asked": 100,
           "resolution": "640x480", "tracking_s_per_frame": 0.2, "mapping_s_per_call": 4.0,
           "mapping_s_per_iter": 0.02, "first_mapping_s": 60.0, "s_per_frame": 2.0,
           "s_per_frame_after_first": 0.6, "peak_gpu_memory_mb": 2048.0,
           "peak_gpu_reserved_mb": 3072.0, "ate_se3_cm": 1.5, "ate_origin_cm": 9.9}
    short = {"sequence": "room-0-loop", "kind": "synthetic", "frames": 3,
             "first_mapping_s_per_iter": 0.03, "accuracy_error": "too few poses"}
    rows = report.rows([{"preset": "paper", "runs": [run, short]},
                        {"preset": "cpu", "only": "real", "failed": "killed at the hard limit"},
                        {"preset": "cpu", "runs": [{"sequence": "x", "error": "a\nboom"}]}])
    assert rows[0]["frames"] == "40/100" and rows[0]["ATE cm"] == 1.5  # se3 on real frames
    assert rows[0]["GPU alloc GiB"] == 2.0 and rows[0]["GPU reserved GiB"] == 3.0
    assert rows[1]["map s/iter"] == 0.03 and rows[1]["status"] == "too few poses"
    assert rows[2]["status"] == "killed at the hard limit"
    assert rows[3]["status"] == "error: boom"
    assert report.paper_row()["track s/f"] == 0.30


def test_bandwidth_table_reads_a_report() -> None:
    render = _bench_module("render_results")
    agent = {"bytes_per_sensor_s": 34_000.0,
             "by_type": {"submap": {"bytes_per_sensor_s": 13_000.0}},
             "server_copy": {"psnr_server_vs_local_db": 55.0, "depth_diff_cm": 0.01}}
    summary = {"bytes_per_sensor_s_mean": 34_000.0, "joint_ate_cm": 0.2,
               "origin_ate_cm": {"0": 0.3, "1": 0.4}, "merged": {"0": True, "1": True}}
    report = {"preset": "cpu", "frames": "0:300:6",
              "variants": {"after": {"agents": {"0": agent}, "summary": summary, "wall_s": 9}},
              "ratio_after_over_before": {"bytes_per_sensor_s": 0.34, "joint_ate": 1.01}}
    text = render._bandwidth(report)
    assert "| after | 0 | 34.0 | 13.0 | 55.0 | 0.01 |" in text
    assert "| after | 34.0 | 0.2 | 0.3 / 0.4 | - | 0, 1 | 9 |" in text
    assert "x0.34" in text and "x1.01" in text
    summary["loops"] = {"found": 7, "accepted": 6, "skipped": 39}
    assert "| after | 34.0 | 0.2 | 0.3 / 0.4 | 6 / 7 (39) | 0, 1 | 9 |" in render._bandwidth(report)


def test_faults_bench_counts_dropped_decoders_apart_from_losses() -> None:
    fault_run = _bench_module("fault_run")
    kept, decoders = fault_run.split_drops({
        "another incarnation": 3,
        "decoder delta against the agent's seq 2, the server holds its weights of seq 9": 1,
        "decoder delta against 0#7, a group decoder this server does not hold": 2,
        "seq too far ahead": 2})
    assert decoders == 3 and kept == {"seq too far ahead": 2}
    zero = dict.fromkeys((*fault_run.LOSS_COUNTS, "foreign_points_missing",
                          "updates_unconfirmed", "decoder_stale"), 0)
    row = {"lost": {"0": zero, "1": zero}, "server_bus_dropped": {}}
    assert fault_run.nothing_lost(row)
    assert not fault_run.nothing_lost({**row, "lost_key": None}), "the fault never happened"
    assert not fault_run.nothing_lost({**row, "lost": {"0": {**zero, "points_lost": 1}}})


def test_faults_table_reads_a_report() -> None:
    render = _bench_module("render_results")
    lost = {"frames_lost": 0, "keyframes_lost": 0, "points_lost": 0, "points_stale": 0,
            "unacknowledged": 0, "dropped_by_server": 0, "resent": 2}
    base = {"fault_at_frame": 5, "lost": {"0": lost, "1": lost}, "nothing_lost": True,
            "joint_ate_m": 0.02, "ate_ratio": 1.0}
    report = {"preset": "tiny", "frames": ["0:9:3", "3:12:3"], "seq": "/d/kitchen",
              "scenarios": {"none": base,
                            "agent_refused": {**base, "joint_ate_m": 0.021, "ate_ratio": 1.05,
                                              "refused_exit_code": 5,
                                              "first_incarnation_intact": True,
                                              "refused_messages_dropped": 1}},
              "partition": {"skipped": "no iproute2"}}
    text = render._faults(report)
    assert "| none | True | 0 / 0 / 0 (+0 stale) | 0 | 0 | 4 | 2.00 | 1.0 |  |" in text
    assert "| agent_refused | True |" in text and "exit 5, first incarnation intact: True" in text
    assert "| partition | skipped | no iproute2 |" in text
    report["by_seed"] = {"0": {}, "1": {}}
    report["over_seeds"] = {
        "none": {"ate_mean_m": 0.02, "ratio_of_means": 1.0, "ratios": [1.0, 1.0],
                 "nothing_lost": True, "spread": 1.08},
        "agent_refused": {"ate_mean_m": 0.0215, "ratio_of_means": 1.075, "ratios": [1.05, 1.1],
                          "nothing_lost": True}}
    text = render._faults(report)
    assert "| agent_refused | True | 2.15 | 1.075 | 1.05, 1.1 |" in text
    assert "under run seeds 0, 1" in text and "over the seeds: 1.08" in text


@pytest.mark.slow
def test_faults_bench_a_lost_message_is_resent_and_nothing_is_lost(tmp_path: Path) -> None:
    """A tiny run of the bench itself: the fault-free run and one lost agent message."""
    import json

    faults = _bench_module("faults")
    out = tmp_path / "faults.json"
    faults.main(["--only", "agent_msg_lost", "--frames", "0:18:3,6:24:3", "--fault-at", "2",
                 "--seeds", "0", "1", "--out", str(tmp_path / "runs"), "--json", str(out)])
    report = json.loads(out.read_text())
    lossy = report["scenarios"]["agent_msg_lost"]
    assert lossy["lost_key"].endswith(("/keyframe", "/submap", "/decoder", "/frames"))
    assert lossy["lost"]["1"]["resent"] >= 1
    assert lossy["nothing_lost"] and report["scenarios"]["none"]["nothing_lost"]
    assert lossy["joint_ate_m"] is not None and "partition" not in report
    # Over both seeds: the first seed's rows are the table's, the means follow from by_seed.
    assert list(report["by_seed"]) == ["0", "1"]
    assert report["by_seed"]["0"]["agent_msg_lost"]["joint_ate_m"] == lossy["joint_ate_m"]
    over = report["over_seeds"]["agent_msg_lost"]
    ates = [report["by_seed"][s]["agent_msg_lost"]["joint_ate_m"] for s in ("0", "1")]
    assert over["ate_mean_m"] == pytest.approx(sum(ates) / 2)
    assert len(over["ratios"]) == 2 and over["nothing_lost"]
    assert report["over_seeds"]["none"]["spread"] >= 1.0


def test_pose_graph_cost_bench_measures_a_graph_that_the_loops_correct() -> None:
    from cpslam.common.config import load_config

    bench = _bench_module("pose_graph_cost")
    row = bench.measure(load_config("tiny", env={}).pose_graph, 3, 100, 10, 1, 0)
    assert row["nodes"] == 300 and row["edges"] == 3 * 99 + row["loops"] and row["loops"] == 60
    # 1 mm / 0.05 degree drift per keyframe against 5 mm loops: the graph must pull it back
    assert row["rmse_after_m"] < 0.6 * row["rmse_before_m"]
    text = _bench_module("render_results").RENDERERS["pose_graph_cost"](
        {"preset": "tiny", "loop_every": 10, "rows": [row]})
    assert "| 3 | 100 | 300 |" in text


def test_depth_codec_bench_measures_and_renders() -> None:
    bench, render = _bench_module("depth_codec"), _bench_module("render_results")
    rng = np.random.default_rng(0)
    wall = np.broadcast_to(np.linspace(1.0, 3.0, 64), (48, 64))
    depth = (wall + rng.normal(0.0, 1e-3, wall.shape) * wall**2).astype(np.float32)
    row = bench.measure([depth], 0.5, 1.3)
    assert row["size"] == [32, 24] and row["png"]["bytes"] > 0 and row["zstd-delta"]["bytes"] > 0
    text = render._depth_codec({"images": 1, "data": "wall", "frames": "0:1", "rows": [row]})
    assert f"| 32 x 24 | 1.3 | {row['png']['bytes']} | {row['zstd-delta']['bytes']} |" in text


def test_wire_fields_splits_a_recording_by_topic_and_field(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]
                                                           ) -> None:
    from cpslam import protocol
    from cpslam.agent.deltas import encode_features
    from cpslam.agent.recording import WireRecorder
    from cpslam.protocol.samples import sample

    base = sample("submap_delta", n_points=500, feature_dim=16)
    fields, _ = encode_features(base.feature_values(), "int8")
    msg = base.model_copy(update={"features": None, **fields})
    keyframe = sample("keyframe", descriptor_dim=256)
    rec = WireRecorder(tmp_path / "wire.rec", "a", "s", 1)
    for i in range(2):
        rec.message(float(i), "submap", protocol.encode(msg))
    rec.message(2.0, "keyframe", protocol.encode(keyframe))
    rec.close()
    bench = _bench_module("wire_fields")
    topics = bench.field_bytes([tmp_path / "wire.rec"])
    assert sorted(topics) == ["keyframe", "submap"]
    submap = topics["submap"]
    assert submap["messages"] == 2 and submap["wire"] == 2 * len(protocol.encode(msg))
    assert submap["fields"]["features_int8"]["raw"] == 2 * 500 * 16
    assert submap["fields"]["feature_scales"]["raw"] == 2 * 500 * 2  # float16
    assert submap["fields"]["xyz_local"]["raw"] == 2 * 500 * 3 * 4  # int32 counts
    for f in submap["fields"].values():
        assert f["zstd"] <= f["raw"]
    # sorted ids with their filter compress far below their 8 bytes each
    assert submap["fields"]["point_ids"]["zstd"] < 0.5 * submap["fields"]["point_ids"]["raw"]
    bench.print_breakdown(topics)
    out = capsys.readouterr().out
    assert "submap: 2 messages" in out and "features_int8" in out
