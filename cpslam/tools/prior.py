"""Fit a decoder prior on synthetic scenes (`cpslam prior OUT`; see common/field/prior.py).

The odometry runs in lock-step over the first frames of each scene in turn, room loops and
apartment walks, every other pair with depth noise; each scene starts from the decoders the
previous one ended with, and the first from `run.seed`'s random weights. The feature CNN stays
the first scene's (it is never trained). What is written: the last scene's decoders and that
CNN, the prior of the preset's field widths. Nothing here reads ground truth; the scenes are
rendered on the fly from their seeds, so the same command gives the same file on a CPU.

The bundled `cpu.npz` (the `cpu` preset's widths) came from the first example in `--help`;
its scene seeds (9000-9003) are apart from the benches' (0-7, 200-203 and 300-303), so no
bench scene was seen in fitting.
"""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail
from cpslam.common.config.cli import DeviceOpt, PresetOpt, SetOpt

logger = logging.getLogger(__name__)

__all__ = ["fit_prior", "prior"]


def fit_prior(out: Path, preset: str, overrides: list[str], scenes: int, scene_base: int,
              frames: int, show_progress: bool = False) -> dict:
    """Fit and write the prior; returns what was done (scenes, frames, seconds, path)."""
    from cpslam.agent.odometry import Odometry
    from cpslam.common.config import load_config
    from cpslam.common.datasets import open_sequence
    from cpslam.common.device import configure_torch, resolve_device
    from cpslam.common.field.prior import save_prior
    from cpslam.common.logs import progress
    from cpslam.tools.synth import generate
    from cpslam.tools.synth.cycle import scene_cycle

    start = time.perf_counter()
    done = []
    with tempfile.TemporaryDirectory(prefix="cpslam-prior-") as tmp:
        previous: Path | None = None
        for spec in scene_cycle(scenes, scene_base):
            kind, seed, noise = spec["kind"], spec["seed"], spec["noise"]
            folder = Path(tmp) / f"{kind}-{seed}"
            generate(folder, scene=kind, frames=frames, width=320, height=240, seed=seed,
                     noise=noise, loop=spec["loop"], overwrite=True)
            start_from = f"field.prior={previous}" if previous else "field.prior=null"
            cfg = load_config(preset, overrides=[*overrides, "run.schedule=lockstep",
                                                 start_from], env={})
            configure_torch(cfg.run.num_threads, cfg.run.deterministic, 1)
            seq = open_sequence(str(folder / "agent_0"))
            device = resolve_device(cfg.run.device)
            odometry = Odometry.from_config(cfg, seq.intrinsics, device)
            for index in progress(range(len(seq)), desc=f"{kind}-{seed}",
                                  disable=not show_progress):
                odometry.step(seq[index])
            odometry.close()
            previous = Path(tmp) / f"prior-{len(done)}.npz"
            save_prior(previous, odometry.decoders, odometry.cnn)
            done.append({"scene": kind, "seed": seed, "noise": noise, "frames": len(seq)})
            logger.info("prior: fitted on %s %d (%d frames)", kind, seed, len(seq))
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(previous.read_bytes())
    return {"path": str(out), "preset": preset, "overrides": overrides, "device": device,
            "scenes": done, "seconds": round(time.perf_counter() - start, 1)}


def prior(
    out: Annotated[Path, typer.Argument(help="Where to write the prior (.npz).")],
    overwrite: OverwriteOpt = False,
    preset: PresetOpt = "cpu",
    sets: SetOpt = None,
    scenes: Annotated[int, typer.Option(min=1, help="Synthetic scenes to fit on.")] = 4,
    scene_base: Annotated[int, typer.Option(help="Seed of the first scene.")] = 9000,
    frames: Annotated[int, typer.Option("--num-frames", min=2, help="Frames of each scene.")
                      ] = 30,
    device: DeviceOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Fit start weights of the decoders and feature CNN on synthetic scenes (field.prior).

    Room loops and apartment walks rendered from their seeds, one after the other, in
    lock-step; no ground truth is read. Point field.prior at the file to use it. The
    bundled cpu.npz came from the first example; other field widths need their own prior
    (the third).

    Examples:

      cpslam prior cpu.npz --preset cpu --set mapping.iters_first=300

      cpslam prior mine.npz --scenes 8 --num-frames 60

      cpslam prior wide.npz --set field.c_hidden=128
    """
    import json

    if out.suffix != ".npz":
        fail(f"prior: OUT must end in .npz, got {out}")
    check_output(out, overwrite)
    overrides = [*(sets or []), *([f"run.device={device}"] if device else [])]
    try:
        result = fit_prior(out, preset, overrides, scenes, scene_base, frames,
                           show_progress=not as_json)
    except (FileNotFoundError, ValueError, KeyError) as err:
        fail(str(err))
    if as_json:
        typer.echo(json.dumps(result, indent=2))
    else:
        typer.echo(f"prior for {preset} ({scenes} scenes x {frames} frames, "
                   f"{result['seconds']:.0f} s) -> {result['path']}")
