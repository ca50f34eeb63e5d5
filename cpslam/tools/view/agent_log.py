"""An agent logging itself to Rerun while it runs (`run.rerun`, docs/viewer.md).

`AgentRecorder` is called once per processed frame with the frame, its `FrameResult` and the
odometry: it logs the tracked pose on the `stamp` timeline every frame, each keyframe as a
frustum with its thumbnail, and, at most every `every_s` seconds, the trajectory line, the
map's points (thinned to `max_points`) and the tracking numbers. What it logs goes through
the same `Scene` as `cpslam view`, at the same entity paths. Rerun batches and sends from a
thread of its own, so a frame costs the agent a few small log calls; the map points, the
largest item, are sent only every `every_s`.

The daemons never import this module unless `run.rerun` asks for it (`cpslam-agent` builds
the recorder and hands it to the run as a frame callback).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cpslam.tools.view.sink import Scene, open_recording

logger = logging.getLogger(__name__)

__all__ = ["AgentRecorder", "MODES"]

MODES = ("save", "spawn", "connect")
LIVE_FILE = "live.rrd"
"""`run.rerun: save` writes RUN/agent_<id>/live.rrd."""


class AgentRecorder:
    """Logs one agent's frames to a Rerun recording (see the module docstring).

    Args:
        agent_id: the agent's id (entity paths ``world/agents/<id>/...``).
        mode: ``save`` (to `agent_dir`/live.rrd), ``spawn`` (a native viewer) or ``connect``
            (a running viewer at `url`).
        agent_dir: the agent's run folder (``save``).
        url: the viewer's gRPC URL (``connect``).
        every_s: seconds between logs of the map points and the trajectory line.
        max_points: at most this many map points per log (evenly thinned).
        clock: monotonic seconds (injectable for tests).
    """

    def __init__(self, agent_id: str, mode: str, agent_dir: Path, url: str,
                 every_s: float = 2.0, max_points: int = 20_000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if mode not in MODES:
            raise ValueError(f"AgentRecorder: mode must be one of {MODES}, got {mode!r}")
        self.agent_id, self.every_s, self.max_points = str(agent_id), every_s, max_points
        self.path = agent_dir / LIVE_FILE if mode == "save" else None
        rec = open_recording(f"agent-{agent_id}", save=self.path,
                             connect=url if mode == "connect" else None)
        self.scene = Scene(rec)
        self._clock = clock
        self._last_full: float | None = None
        self._xyz: list[np.ndarray] = []

    def __call__(self, frame: Any, result: Any, odometry: Any) -> None:
        """Log one processed frame (`RGBDFrame` at processing resolution, its `FrameResult`,
        the `Odometry` whose intrinsics and published map are read)."""
        self.scene.at(stamp_s=result.timestamp)
        T_world_cam = np.asarray(result.T_world_cam)
        self.scene.camera(self.agent_id, T_world_cam)
        self._xyz.append(T_world_cam[:3, 3].copy())
        if result.is_keyframe and result.kf_id is not None:
            self.scene.keyframe(self.agent_id, 0, result.kf_id, T_world_cam,
                                odometry.intrinsics, frame.rgb, static=False)
        self.scene.scalar(f"agents/{self.agent_id}/track_loss", result.track_loss)
        now = self._clock()
        if self._last_full is None or now - self._last_full >= self.every_s:
            self._last_full = now
            self._full(odometry)

    @classmethod
    def from_config(cls, run: Any, agent_id: str, agent_dir: Path) -> AgentRecorder | None:
        """The recorder `run.rerun` asks for (the `run` config section), None when null."""
        if run.rerun is None:
            return None
        return cls(agent_id, run.rerun, agent_dir, run.rerun_url, every_s=run.rerun_every_s)

    def close(self) -> None:
        """Flush and close the recording."""
        self.scene.close()
        if self.path is not None:
            logger.info("Rerun recording of agent %s: %s (open it with: rerun %s)",
                        self.agent_id, self.path, self.path)

    def _full(self, odometry: Any) -> None:
        """The trajectory line, the map's points and their count."""
        self.scene.trajectory(self.agent_id, 0, np.asarray(self._xyz), static=False)
        point_map = odometry.point_map  # the published map: never half written
        n = len(point_map)
        self.scene.scalar(f"agents/{self.agent_id}/points", n)
        if n == 0:
            return
        rows = np.linspace(0, n - 1, min(n, self.max_points)).round().astype(np.int64)
        xyz = point_map.xyz_world().detach().cpu().numpy()[rows]
        colours = point_map.color.cpu().numpy()[rows].astype(np.uint8)
        self.scene.points(f"world/agents/{self.agent_id}/points", xyz, colours, static=False)
