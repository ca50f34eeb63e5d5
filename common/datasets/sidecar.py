"""The optional `camera.yaml` beside a sequence, and how intrinsics are chosen.

Precedence, highest first: the `intrinsics=` argument > the `overrides=` argument (e.g. the
config's `camera.*`) > `camera.yaml` > the format's own files or published defaults > the
image size (width/height only).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import yaml

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets.base import DatasetError

SIDECAR_NAME = "camera.yaml"

_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
_INT_KEYS = ("width", "height")
_POSITIVE_KEYS = ("fx", "fy", "width", "height", "depth_scale", "fps")


@dataclass(frozen=True)
class Sidecar:
    """What a `camera.yaml` says; every field is optional (None = not given)."""

    path: Path | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    width: int | None = None
    height: int | None = None
    depth_scale: float | None = None
    fps: float | None = None

    @classmethod
    def read(cls, root: Path) -> Sidecar:
        """Read `root/camera.yaml`; an empty Sidecar when there is none."""
        path = Path(root) / SIDECAR_NAME
        if not path.is_file():
            return cls()
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as e:
            raise DatasetError(f"{path}: cannot parse YAML ({e})") from e
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise DatasetError(
                f"{path}: expected a mapping of camera keys, got {type(data).__name__}"
            )
        return cls(path=path).updated(data, str(path))

    def updated(self, values: Mapping[str, Any], source: str) -> Sidecar:
        """A copy where `values` (sidecar keys; None entries ignored) take precedence.

        `source` names where the values came from in error messages.
        """
        known = [f.name for f in fields(self) if f.name != "path"]
        checked: dict[str, float | int] = {}
        for key, value in values.items():
            if key not in known:
                raise DatasetError(
                    f"{source}: unknown key {key!r}; allowed keys are " + ", ".join(known)
                )
            if value is not None:
                checked[key] = _check_value(source, key, value)
        return replace(self, **checked)  # type: ignore[arg-type]

    def camera_values(self) -> dict[str, float | int]:
        """The intrinsics keys this sidecar sets."""
        return {k: getattr(self, k) for k in _CAMERA_KEYS if getattr(self, k) is not None}


def resolve_intrinsics(
    root: Path,
    fmt: str,
    sidecar: Sidecar,
    override: Intrinsics | None,
    defaults: dict[str, float | int] | None,
    image_wh: tuple[int, int] | None,
    why_no_defaults: str = "",
) -> Intrinsics:
    """Merge the intrinsics sources by precedence; error naming what is missing.

    Args:
        root: the sequence folder (for messages).
        fmt: the format name (for messages).
        sidecar: the sequence's camera.yaml (possibly empty).
        override: explicit intrinsics; when given they win outright.
        defaults: what the format's own files or published calibration provide.
        image_wh: the depth image size, used for width/height nobody else gave.
        why_no_defaults: why the format could not provide intrinsics (for the message).
    """
    if override is not None:
        return override
    values: dict[str, float | int] = dict(defaults or {})
    values.update(sidecar.camera_values())
    if image_wh is not None:
        values.setdefault("width", image_wh[0])
        values.setdefault("height", image_wh[1])
    missing = [k for k in _CAMERA_KEYS if k not in values]
    if missing:
        reason = f" ({why_no_defaults})" if why_no_defaults else ""
        raise DatasetError(
            f"{root}: no {', '.join(missing)} for this {fmt} sequence{reason}; write them into "
            f"{Path(root) / SIDECAR_NAME} or pass the intrinsics explicitly"
        )
    try:
        return Intrinsics(**{k: values[k] for k in _CAMERA_KEYS})
    except ValueError as e:
        raise DatasetError(f"{root}: invalid intrinsics for this {fmt} sequence: {e}") from e


def _check_value(path: str, key: str, value: object) -> float | int:
    # bool is an int in Python; "width: yes" is a mistake, not 1.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{path}: {key} must be a number, got {value!r}")
    if key in _INT_KEYS and not float(value).is_integer():
        raise DatasetError(f"{path}: {key} must be a whole number of pixels, got {value!r}")
    if not math.isfinite(value) or (key in _POSITIVE_KEYS and value <= 0):
        raise DatasetError(
            f"{path}: {key} must be a finite positive number, got {value!r}"
            if key in _POSITIVE_KEYS
            else f"{path}: {key} must be a finite number, got {value!r}"
        )
    return int(value) if key in _INT_KEYS else float(value)
