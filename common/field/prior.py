"""Decoder priors: starting weights for the decoders and the feature CNN, kept in an .npz.

Decoders that start from random weights spend most of the first mapping call learning what
any scene's occupancy and colour look like from point features and offsets; weights fitted
once on other scenes start the call from there. A prior holds the decoders' state (keys
`decoders.<name>`) and the feature CNN's (`cnn.<name>`): the decoders were fitted to that
CNN's features, so the two travel together. `cpslam.tools.prior` fits one on synthetic
scenes; the bundled priors live in this package's `priors/` folder.

Plain numpy arrays, no pickle: loading a prior runs no code from the file.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

__all__ = ["BUNDLED", "apply_prior", "load_prior", "resolve_prior", "save_prior"]

BUNDLED = Path(__file__).resolve().parent / "priors"
# A prior is a few decoders' worth of weights; anything far larger is not one.
_MAX_BYTES = 64 * 1024 * 1024


def resolve_prior(name: str) -> Path:
    """A bare file name is one of the bundled priors; anything with a folder is a path."""
    path = Path(name).expanduser()
    if path.parent == Path("."):
        path = BUNDLED / path
    if not path.is_file():
        bundled = sorted(p.name for p in BUNDLED.glob("*.npz"))
        raise FileNotFoundError(f"field.prior: no file {path} (bundled priors: "
                                f"{', '.join(bundled) or 'none'})")
    return path


def save_prior(path: Path, decoders: nn.Module, cnn: nn.Module) -> None:
    """Write the decoders' and the CNN's weights as float32 arrays."""
    arrays = {f"decoders.{k}": v.detach().float().cpu().numpy()
              for k, v in decoders.state_dict().items()}
    arrays.update({f"cnn.{k}": v.detach().float().cpu().numpy()
                   for k, v in cnn.state_dict().items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def load_prior(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a prior file (read once per process while the file stays the same)."""
    stat = path.stat()
    if stat.st_size > _MAX_BYTES:
        raise ValueError(f"field.prior: {path} is {stat.st_size} bytes, more than a prior's "
                         f"{_MAX_BYTES}")
    return _read(path, stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=4)
def _read(path: Path, mtime_ns: int, size: int) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"field.prior: {path} is not a prior .npz ({exc})") from exc
    for key, value in arrays.items():
        if value.dtype != np.float32:
            raise ValueError(f"field.prior: {path}: {key} is {value.dtype}, expected float32")
    return arrays


def apply_prior(module: nn.Module, path: Path, prefix: str) -> None:
    """Load `module`'s weights from the prior at `path` (its keys under `prefix.`); the file
    must hold exactly the module's parameters, with the module's shapes."""
    arrays = load_prior(path)
    own = module.state_dict()
    keys = {k[len(prefix) + 1:] for k in arrays if k.startswith(prefix + ".")}
    if keys != set(own):
        missing, extra = sorted(set(own) - keys), sorted(keys - set(own))
        raise ValueError(f"field.prior: {path} does not fit the {prefix} (missing "
                         f"{missing}, unexpected {extra}): it was fitted with other "
                         f"field widths")
    state = {}
    for key, tensor in own.items():
        value = arrays[f"{prefix}.{key}"]
        if tuple(value.shape) != tuple(tensor.shape):
            raise ValueError(f"field.prior: {path}: {prefix}.{key} has shape "
                             f"{tuple(value.shape)}, these field widths need "
                             f"{tuple(tensor.shape)}")
        state[key] = torch.from_numpy(value.copy()).to(tensor.dtype)
    module.load_state_dict(state)
