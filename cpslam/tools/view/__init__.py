"""`cpslam view`: a 3-D view of runs in Rerun (the optional ``rerun-sdk``, extra ``cpslam[viz]``).

- `replay` logs a finished run folder (trajectories against ground truth, keyframes as camera
  frusta with thumbnails, the fused map, the mesh, the pose graph and the loops);
- `live` is an observer of a running session that only listens to the wire protocol;
- `sink` holds what both share: opening a recording (viewer, file or web viewer) and the
  entity layout (docs/viewer.md is the reference).

Nothing here is imported by the daemons; rerun itself is imported only inside functions, so
that `cpslam --help` works without it and the missing extra gives a clear message.
"""

from __future__ import annotations

INSTALL_HINT = "pip install 'cpslam[viz]'"
"""How to get rerun-sdk; said by every error about it missing."""


class RerunMissingError(RuntimeError):
    """rerun-sdk is not installed."""


def import_rerun():
    """The ``rerun`` module, or `RerunMissingError` saying how to install it."""
    try:
        import rerun
    except ImportError as err:
        raise RerunMissingError(
            f"cpslam view needs the rerun-sdk package, which is not installed ({err}); "
            f"install it with: {INSTALL_HINT}") from None
    return rerun
