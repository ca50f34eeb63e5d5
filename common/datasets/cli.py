"""`cpslam dataset info`: what a sequence folder holds, as text or JSON; `cpslam dataset gt`:
its ground truth as a TUM file (for evo and other tools).

The lead's umbrella CLI registers `info` as a command; heavy imports stay inside functions so
that `cpslam --help` does not pay for them. `FormatOpt` and `FramesOpt` are the options of
every command that opens a sequence folder (also `cpslam eval ate`), so the flags read the
same everywhere; both are passed on to `open_sequence` as they are. The `Topic*Opt` options
name a bag's topics (`cpslam dataset info`, `cpslam-agent`, `cpslam run`); `topics_arg`
turns them into `open_sequence`'s `topics`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail

if TYPE_CHECKING:
    from cpslam.common.datasets.base import RGBDSequence

FormatOpt = Annotated[
    str | None,
    typer.Option("--format", "-f", help="Dataset format: replica, tum, 7scenes, scannet or bag "
                 "(default: detect from the folder's layout or the bag's file name)."),
]
FramesOpt = Annotated[
    str | None,
    typer.Option("--frames", help="Frame selection START:STOP[:STEP] of a dataset folder, "
                 "e.g. 0:300 or ::2 (frames keep their own indices and timestamps)."),
]

TopicRgbOpt = Annotated[
    str | None,
    typer.Option("--topic-rgb", help="Bags: colour topic, sensor_msgs/Image or "
                 "CompressedImage (default: the only colour image topic)."),
]
TopicDepthOpt = Annotated[
    str | None,
    typer.Option("--topic-depth", help="Bags: depth topic, Image 16UC1/32FC1 or "
                 "CompressedImage compressedDepth (default: the only depth image topic)."),
]
TopicInfoOpt = Annotated[
    str | None,
    typer.Option("--topic-info", help="Bags: sensor_msgs/CameraInfo topic for the intrinsics "
                 "(default: the only one, or the one beside the depth topic)."),
]
TopicPoseOpt = Annotated[
    str | None,
    typer.Option("--topic-pose", help="Bags: ground-truth pose topic (PoseStamped, "
                 "PoseWithCovarianceStamped, TransformStamped or Odometry; tf as "
                 "/tf:PARENT:CHILD), for evaluation only; 'none' reads none (default: the "
                 "only pose topic, if any)."),
]


def topics_arg(
    rgb: str | None, depth: str | None, info: str | None, pose: str | None
) -> dict[str, str] | None:
    """The `--topic-*` options as `open_sequence(topics=...)`, None when none is given."""
    given = {"rgb": rgb, "depth": depth, "info": info, "pose": pose}
    return {k: v for k, v in given.items() if v is not None} or None


def info(
    path: Annotated[Path, typer.Argument(help="Sequence folder, or a bag (ROS 1 .bag, .mcap, "
                                         ".db3, ROS 2 bag folder).", show_default=False)],
    format: FormatOpt = None,
    frames: FramesOpt = None,
    samples: Annotated[
        int, typer.Option("--samples", min=1, help="Frames sampled for the depth statistics.")
    ] = 5,
    as_json: JsonOpt = False,
    camera: Annotated[
        list[str] | None,
        typer.Option("--camera", help="Override a camera.yaml key, e.g. --camera fx=525 "
                     "(fx, fy, cx, cy, width, height, depth_scale, fps; repeatable)."),
    ] = None,
    topic_rgb: TopicRgbOpt = None,
    topic_depth: TopicDepthOpt = None,
    topic_info: TopicInfoOpt = None,
    topic_pose: TopicPoseOpt = None,
) -> None:
    """Describe an RGB-D sequence: format, frames, resolution, intrinsics, depth, ground truth.

    Examples:

      cpslam dataset info runs/data/room/agent_0

      cpslam dataset info ../shared/data/7scenes-kitchen-0-299 --frames 0:100 --json

      cpslam dataset info my_tum_sequence --camera fx=525 --camera fy=525 --camera cx=319.5

      cpslam dataset info robot.bag --topic-rgb /camera/color/image_raw --frames 0:300
    """
    from cpslam.common.datasets import DatasetError, open_sequence

    try:
        overrides = _parse_camera(camera or [])
        topics = topics_arg(topic_rgb, topic_depth, topic_info, topic_pose)
        sequence = open_sequence(path, fmt=format, frames=frames, overrides=overrides or None,
                                 topics=topics)
        summary = summarize(sequence, samples=samples)
    except DatasetError as e:
        fail(str(e))
    if as_json:
        from cpslam.common.rundir import SCHEMA_VERSION

        typer.echo(json.dumps({"schema_version": SCHEMA_VERSION, **summary}, indent=2))
    else:
        typer.echo(format_summary(summary))


def gt(
    path: Annotated[Path, typer.Argument(help="Sequence folder, or a bag (ROS 1 .bag, .mcap, "
                                         ".db3, ROS 2 bag folder).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="The TUM file to write.",
                                      show_default=False)],
    format: FormatOpt = None,
    frames: FramesOpt = None,
    overwrite: OverwriteOpt = False,
    topic_rgb: TopicRgbOpt = None,
    topic_depth: TopicDepthOpt = None,
    topic_info: TopicInfoOpt = None,
    topic_pose: TopicPoseOpt = None,
) -> None:
    """Write a sequence's ground truth as a TUM file, for evo and other tools.

    One line (`stamp tx ty tz qx qy qz qw`) per frame that has a ground-truth pose, with the
    frames' own timestamps, to compare with a run's trajectory.tum (docs/evaluation.md).

    Examples:

      cpslam dataset gt runs/data/room/agent_0 --out gt.tum

      cpslam dataset gt ../shared/data/7scenes-kitchen-0-299 --frames 0:100 --out gt.tum

      cpslam dataset gt robot.bag --topic-pose /vicon/camera --out gt.tum
    """
    import numpy as np

    from cpslam.common.datasets import DatasetError, open_sequence
    from cpslam.common.trajectory import write_tum

    check_output(out, overwrite)
    try:
        sequence = open_sequence(path, fmt=format, frames=frames,
                                 topics=topics_arg(topic_rgb, topic_depth, topic_info,
                                                   topic_pose))
    except DatasetError as e:
        fail(str(e))
    poses = sequence.gt_poses()
    if poses is None:
        fail(f"{path}: the sequence has no ground truth (expected a ground-truth file of its "
             f"format, or a pose topic for a bag)")
    known = np.all(np.isfinite(poses.reshape(len(poses), 16)), axis=1)
    if not known.any():
        fail(f"{path}: no frame of the selection has a ground-truth pose")
    write_tum(out, np.asarray(sequence.timestamps, dtype=np.float64)[known], poses[known])
    typer.echo(f"{int(known.sum())}/{len(sequence)} frames with ground truth → {out}")


def summarize(sequence: RGBDSequence, samples: int = 5) -> dict[str, Any]:
    """Facts about a sequence; depth statistics from `samples` evenly spaced frames."""
    import numpy as np

    n = len(sequence)
    positions = np.unique(np.linspace(0, n - 1, min(samples, n)).round().astype(int))
    valid_depth = []
    pixels = 0
    for p in positions:
        depth = sequence[int(p)].depth
        valid_depth.append(depth[depth > 0])
        pixels += depth.size
    valid = np.concatenate(valid_depth)
    depth_stats: dict[str, Any] = {
        "sampled_indices": [int(sequence.indices[p]) for p in positions],
        "valid_fraction": float(valid.size / pixels),
        "min_m": float(valid.min()) if valid.size else None,
        "median_m": float(np.median(valid)) if valid.size else None,
        "max_m": float(valid.max()) if valid.size else None,
    }

    gt: dict[str, Any] = {"present": sequence.has_gt, "frames": 0, "trajectory_length_m": None}
    poses = sequence.gt_poses()
    if poses is not None:
        known = np.all(np.isfinite(poses.reshape(n, 16)), axis=1)
        xyz = poses[known, :3, 3]
        gt["frames"] = int(known.sum())
        gt["trajectory_length_m"] = float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())

    camera = sequence.intrinsics
    topics = getattr(sequence, "topics", None)  # bags only
    return {
        **({"topics": topics} if topics is not None else {}),
        "format": sequence.format,
        "path": str(sequence.path),
        "frames": n,
        "first_index": int(sequence.indices[0]),
        "last_index": int(sequence.indices[-1]),
        "duration_s": float(sequence.timestamps[-1] - sequence.timestamps[0]),
        "width": camera.width,
        "height": camera.height,
        "intrinsics": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy},
        "fps": sequence.fps,
        "depth_scale": sequence.depth_scale,
        "depth": depth_stats,
        "ground_truth": gt,
    }


def format_summary(summary: dict[str, Any]) -> str:
    """The text form of `summarize`'s result."""
    k = summary["intrinsics"]
    d = summary["depth"]
    g = summary["ground_truth"]
    if d["min_m"] is None:
        depth = f"no valid depth in {len(d['sampled_indices'])} sampled frames"
    else:
        depth = (
            f"{d['min_m']:.3f} / {d['median_m']:.3f} / {d['max_m']:.3f} m (min / median / max "
            f"over {len(d['sampled_indices'])} frames), {100 * d['valid_fraction']:.1f}% valid"
        )
    if g["present"]:
        truth = (
            f"yes, {g['frames']}/{summary['frames']} frames, trajectory "
            f"{g['trajectory_length_m']:.2f} m (evaluation only)"
        )
    else:
        truth = "no"
    rows = [
        ("format", summary["format"]),
        ("path", summary["path"]),
        *(
            [("topics", ", ".join(f"{k} {v}" for k, v in summary["topics"].items() if v))]
            if "topics" in summary
            else []
        ),
        (
            "frames",
            f"{summary['frames']} (indices {summary['first_index']}.."
            f"{summary['last_index']}, {summary['duration_s']:.2f} s)",
        ),
        ("resolution", f"{summary['width']}x{summary['height']}"),
        ("intrinsics", f"fx={k['fx']:g} fy={k['fy']:g} cx={k['cx']:g} cy={k['cy']:g}"),
        ("fps", f"{summary['fps']:g}"),
        ("depth scale", f"{summary['depth_scale']:g} units/m"),
        ("depth", depth),
        ("ground truth", truth),
    ]
    return "\n".join(f"{name:<13}{value}" for name, value in rows)


def _parse_camera(items: list[str]) -> dict[str, float]:
    """`["fx=525", "cy=239.5"]` -> `{"fx": 525.0, "cy": 239.5}`; errors name the item."""
    from cpslam.common.datasets import DatasetError

    out: dict[str, float] = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[key.strip()] = float(value)
        except ValueError:
            raise DatasetError(f"--camera {item!r}: expected KEY=NUMBER, e.g. fx=525") from None
    return out
