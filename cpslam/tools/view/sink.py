"""Where a view goes (native viewer, ``.rrd`` file or web viewer) and the entity layout that
the replay and the live observer share (docs/viewer.md, "Entity paths").

World entities are in metres in the frame each agent's poses are given in: its group's frame
once merged, its own first camera before (unmerged agents therefore overlap near the origin).
Camera frusta use OpenCV axes (x right, y down, z forward), as every pose in cpslam does.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.tools.view import import_rerun

logger = logging.getLogger(__name__)

__all__ = ["ACCEPTED", "REJECTED", "Scene", "agent_colour", "open_recording"]

APP_ID = "cpslam"
# Distinct colours for up to eight agents (then they repeat), readable on the dark viewer.
AGENT_COLOURS = np.array([(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48),
                          (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60)],
                         dtype=np.uint8)
ACCEPTED = (40, 220, 40)
REJECTED = (230, 40, 40)
EDGE = (160, 160, 160)
GROUND_TRUTH = (200, 200, 200)
THUMBNAIL_WIDTH = 160
"""Keyframe thumbnails are stored at most this wide (JPEG), which keeps recordings small."""


def agent_colour(index: int) -> np.ndarray:
    """RGB uint8 [3] of the agent with this index (order of first appearance)."""
    return AGENT_COLOURS[int(index) % len(AGENT_COLOURS)]


def open_recording(name: str, save: Path | None = None, web: bool = False,
                   web_port: int | None = None, connect: str | None = None) -> Any:
    """A `rerun.RecordingStream` with the cpslam layout, sent to `save` (an ``.rrd`` file),
    to a web viewer served from this process (`web`), to a running viewer at `connect` (its
    gRPC URL), or else to a spawned native viewer."""
    rr = import_rerun()
    rec = rr.RecordingStream(APP_ID, recording_id=name)
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(save), default_blueprint=_blueprint())
    elif connect is not None:
        rec.connect_grpc(connect, default_blueprint=_blueprint())
    elif web:
        url = rec.serve_grpc(default_blueprint=_blueprint())
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=url)
        logger.warning("web viewer: http://localhost:%s/?url=%s (Ctrl-C ends it)",
                       web_port or 9090, url)
    else:
        rec.spawn(default_blueprint=_blueprint())
    return rec


def _blueprint() -> Any:
    """3-D view of the world (the by-agent colouring hidden), time series and event log."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="/world", name="map",
                          contents=["+ /world/**", "- /world/map/by_agent"]),
        rrb.Vertical(rrb.TimeSeriesView(origin="/status", name="server status"),
                     rrb.TextLogView(origin="/events", name="events")),
        column_shares=[3, 1]))


class Scene:
    """Logs cpslam objects to a recording at their documented entity paths."""

    def __init__(self, rec: Any) -> None:
        self.rr = import_rerun()
        self.rec = rec
        self.rec.log("world", self.rr.ViewCoordinates.RDF, static=True)

    # -- time ---------------------------------------------------------------------------

    def at(self, stamp_s: float | None = None, run_s: float | None = None) -> None:
        """Set the `stamp` (data set clock) and/or `run_time` (server clock) timelines."""
        if stamp_s is not None:
            self.rec.set_time("stamp", duration=float(stamp_s))
        if run_s is not None:
            self.rec.set_time("run_time", duration=float(run_s))

    # -- agents -------------------------------------------------------------------------

    def trajectory(self, agent: str, index: int, xyz: np.ndarray, kind: str = "trajectory",
                   static: bool = True) -> None:
        """``world/agents/<a>/<kind>``: a line through positions [N, 3] (kind ``trajectory``
        or ``ground_truth``)."""
        colour = GROUND_TRUTH if kind == "ground_truth" else agent_colour(index)
        xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
        self.rec.log(f"world/agents/{agent}/{kind}",
                     self.rr.LineStrips3D([xyz], colors=[colour], radii=[0.01]), static=static)

    def camera(self, agent: str, T_world_cam: np.ndarray) -> None:
        """``world/agents/<a>/camera``: the agent's current pose (on the active timelines)."""
        self.rec.log(f"world/agents/{agent}/camera", _transform(self.rr, T_world_cam))

    def keyframe(self, agent: str, index: int, kf_id: int, T_world_cam: np.ndarray,
                 intr: Intrinsics | None, rgb: np.ndarray | None = None,
                 static: bool = True) -> None:
        """``world/agents/<a>/keyframes/<kf>``: pose and camera frustum; with `rgb` [H, W, 3]
        uint8 also ``…/image``, a JPEG thumbnail shown in the frustum."""
        path = f"world/agents/{agent}/keyframes/{int(kf_id)}"
        self.rec.log(path, _transform(self.rr, T_world_cam), static=static)
        if intr is None:
            return
        if rgb is not None:
            rgb, intr = _thumbnail(rgb, intr)
        self.rec.log(path, self.rr.Pinhole(
            focal_length=[intr.fx, intr.fy], principal_point=[intr.cx, intr.cy],
            resolution=[intr.width, intr.height], camera_xyz=self.rr.ViewCoordinates.RDF,
            image_plane_distance=0.15, color=agent_colour(index)), static=static)
        if rgb is not None:
            import cv2

            ok, jpeg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])
            if ok:
                self.rec.log(f"{path}/image", self.rr.EncodedImage(
                    contents=jpeg.tobytes(), media_type="image/jpeg"), static=static)

    def points(self, path: str, xyz: np.ndarray, colours: np.ndarray | None,
               static: bool = True) -> None:
        """Points [N, 3] with colours uint8 [N, 3] or [3] at `path` (``world/...``)."""
        xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
        self.rec.log(path, self.rr.Points3D(xyz, colors=colours, radii=[0.01]), static=static)

    def mesh(self, vertices: np.ndarray, triangles: np.ndarray,
             colours: np.ndarray | None) -> None:
        """``world/mesh``: a triangle mesh (vertex colours uint8 [V, 3] or None)."""
        self.rec.log("world/mesh", self.rr.Mesh3D(
            vertex_positions=np.asarray(vertices, np.float32),
            triangle_indices=np.asarray(triangles, np.uint32), vertex_colors=colours),
            static=True)

    # -- pose graph and loops ---------------------------------------------------------------

    def segments(self, path: str, starts: np.ndarray, ends: np.ndarray, colour: Any,
                 labels: list[str] | None = None, static: bool = True) -> None:
        """Line segments between positions [N, 3] and [N, 3] at `path`."""
        starts = np.asarray(starts, np.float32).reshape(-1, 3)
        ends = np.asarray(ends, np.float32).reshape(-1, 3)
        strips = np.stack([starts, ends], axis=1) if len(starts) else np.zeros((0, 2, 3))
        self.rec.log(path, self.rr.LineStrips3D(list(strips), colors=[colour], radii=[0.008],
                                                labels=labels), static=static)

    def loops(self, starts: np.ndarray, ends: np.ndarray, accepted: np.ndarray,
              labels: list[str], static: bool = True) -> None:
        """``world/loops/accepted`` and ``world/loops/rejected``: verified loop pairs, one
        segment between the two keyframes each, labelled with their score."""
        accepted = np.asarray(accepted, dtype=bool)
        for name, mask, colour in (("accepted", accepted, ACCEPTED),
                                   ("rejected", ~accepted, REJECTED)):
            self.segments(f"world/loops/{name}", np.asarray(starts)[mask],
                          np.asarray(ends)[mask], colour,
                          [lb for lb, m in zip(labels, mask, strict=True) if m], static=static)

    # -- events and numbers ---------------------------------------------------------------

    def event(self, kind: str, text: str) -> None:
        """``events/<kind>`` (merges, rounds, loops, agents): a line on the event log."""
        self.rec.log(f"events/{kind}", self.rr.TextLog(text, level="INFO"))

    def scalar(self, name: str, value: float) -> None:
        """``status/<name>``: one value of a time series."""
        self.rec.log(f"status/{name}", self.rr.Scalars(float(value)))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def _transform(rr: Any, T: np.ndarray) -> Any:
    T = np.asarray(T, dtype=np.float64)
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def _thumbnail(rgb: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """The image at most THUMBNAIL_WIDTH wide and its intrinsics (scaled to its own size)."""
    import cv2

    h, w = rgb.shape[:2]
    factor = min(1.0, THUMBNAIL_WIDTH / w)
    if factor < 1.0:
        rgb = cv2.resize(rgb, (max(1, round(w * factor)), max(1, round(h * factor))),
                         interpolation=cv2.INTER_AREA)
    # The image's own size fixes the pinhole, whatever resolution the intrinsics were for.
    return np.ascontiguousarray(rgb), intr.scaled(rgb.shape[1] / intr.width)
