"""Crash-safe files: atomic writes and checked generations.

An atomic write goes to a temporary file in the target's folder, is flushed and fsynced,
renamed over the target and the folder is fsynced: after a crash the target holds either
the old or the new content, never a mix, and once the call returns the new content survives
a power cut. A failed write (a full disk: ``OSError`` ENOSPC) removes its temporary file and
raises; the target is untouched.

A generation file (`save_generation`) is an atomic write of a payload sealed with a trailer
(magic, payload length, SHA-256 of the payload); the file it replaces is kept as
``<name>.prev``. `load_generation` checks the trailer and, when the newest generation is
missing, torn or corrupt, logs the file and why and falls back to the previous one.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import struct
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any, TypeVar

__all__ = [
    "CorruptFileError",
    "atomic_open",
    "fsync_dir",
    "generation_paths",
    "has_generation",
    "load_generation",
    "save_generation",
    "seal",
    "torch_bytes",
    "torch_save_atomic",
    "trailer",
    "unseal",
    "write_bytes_atomic",
    "write_text_atomic",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")

MAGIC = b"CPSLAMG1"
"""Start of a generation trailer; the version digit changes if the trailer layout does."""
_TRAILER = struct.Struct("<8sQ32s")  # magic, payload length, SHA-256 of the payload
PREV_SUFFIX = ".prev"


class CorruptFileError(ValueError):
    """A generation file whose trailer is missing or does not match its payload."""


def fsync_dir(folder: str | Path) -> None:
    """Make a rename or creation inside `folder` durable (no-op where folders cannot be
    opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(
    path: str | Path, mode: str = "wb", encoding: str | None = None,
    previous: str | Path | None = None,
) -> Iterator[IO[Any]]:
    """Open a temporary file next to `path` for writing; on a clean exit it is fsynced and
    renamed over `path` (and the folder fsynced), on an exception it is removed.

    The parent folders are created. `mode` is ``"wb"`` or ``"w"``. With `previous`, an
    existing `path` is moved there just before the new file takes its place (only once the
    new file is complete and fsynced).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open {path}: mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, encoding=encoding if mode == "w" else None) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if previous is not None and path.is_file():
            os.replace(path, previous)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Replace `path` by `data` atomically and durably (see `atomic_open`)."""
    with atomic_open(path, "wb") as f:
        f.write(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str, encoding: str = "utf-8") -> Path:
    """Replace `path` by `text` atomically and durably (see `atomic_open`)."""
    return write_bytes_atomic(path, text.encode(encoding))


def torch_bytes(obj: Any) -> bytes:
    """`obj` as `torch.save` writes it."""
    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def torch_save_atomic(obj: Any, path: str | Path) -> Path:
    """`torch.save(obj, path)`, atomically and durably."""
    return write_bytes_atomic(path, torch_bytes(obj))


def seal(payload: bytes) -> bytes:
    """`payload` followed by its trailer (magic, length, SHA-256)."""
    return payload + trailer(payload)


def trailer(payload: bytes) -> bytes:
    """The integrity trailer of `payload`."""
    return _TRAILER.pack(MAGIC, len(payload), hashlib.sha256(payload).digest())


def unseal(blob: bytes, name: str | Path = "<bytes>") -> bytes:
    """The payload of a sealed `blob`.

    Raises:
        CorruptFileError: the trailer is missing (a torn or foreign file), its length does
            not match (truncated or appended to) or the checksum does not (corrupt).
    """
    if len(blob) < _TRAILER.size:
        raise CorruptFileError(
            f"{name}: {len(blob)} bytes, shorter than the "
            f"{_TRAILER.size}-byte integrity trailer (torn write?)"
        )
    magic, length, digest = _TRAILER.unpack(blob[-_TRAILER.size :])
    if magic != MAGIC:
        raise CorruptFileError(
            f"{name}: no integrity trailer (expected {MAGIC!r} "
            f"{_TRAILER.size} bytes from the end; torn write or not a "
            "cpslam generation file)"
        )
    payload = blob[: -_TRAILER.size]
    if length != len(payload):
        raise CorruptFileError(
            f"{name}: trailer says {length} payload bytes, the file has {len(payload)}"
        )
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptFileError(
            f"{name}: SHA-256 of the payload does not match the trailer (corrupt)"
        )
    return payload


def generation_paths(path: str | Path) -> tuple[Path, Path]:
    """The newest generation file and the previous one (``<name>.prev``)."""
    path = Path(path)
    return path, path.with_name(path.name + PREV_SUFFIX)


def has_generation(path: str | Path) -> bool:
    """Whether a newest or previous generation of `path` exists."""
    return any(p.is_file() for p in generation_paths(path))


def save_generation(path: str | Path, payload: bytes) -> Path:
    """Write `payload` sealed as the newest generation of `path`, durably; the generation it
    replaces becomes ``<name>.prev``.

    The new file is complete and fsynced before the old one is moved: a crash at any point
    leaves a good newest or a good previous generation (`load_generation` finds it).
    """
    path, prev = generation_paths(path)
    with atomic_open(path, "wb", previous=prev) as f:
        f.write(payload)  # and the trailer apart: no second copy of a large state
        f.write(trailer(payload))
    return path


def load_generation(path: str | Path, decode: Callable[[bytes], T]) -> tuple[T, Path]:
    """The newest good generation of `path`, decoded, and the file it came from.

    A newest file that is missing, fails its integrity check or fails `decode` is logged
    (naming the file and the reason) and the previous generation is tried. When that one
    loads, the bad newest file is moved to ``<name>.corrupt`` (kept for a post-mortem): the
    next `save_generation` must not rotate it over the good previous generation.

    Raises:
        FileNotFoundError: neither generation exists.
        CorruptFileError: no generation passes (the message names every file and why).
    """
    reasons = []
    for candidate in generation_paths(path):
        if not candidate.is_file():
            reasons.append(f"{candidate}: missing")
            continue
        try:
            value = decode(unseal(candidate.read_bytes(), candidate))
        except Exception as exc:  # noqa: BLE001 - any unreadable generation falls back
            reason = (
                str(exc)
                if isinstance(exc, CorruptFileError)
                else (f"{candidate}: cannot decode ({type(exc).__name__}: {exc})")
            )
            logger.error("%s; trying the previous generation", reason)
            reasons.append(reason)
            continue
        if reasons:
            newest = generation_paths(path)[0]
            if newest.is_file():
                os.replace(newest, newest.with_name(newest.name + ".corrupt"))
                fsync_dir(newest.parent)
            logger.warning(
                "loaded the previous generation %s (%s); the bad newest file, if any, is "
                "now %s.corrupt",
                candidate,
                "; ".join(reasons),
                newest.name,
            )
        return value, candidate
    if all(r.endswith(": missing") for r in reasons):
        raise FileNotFoundError(f"{path}: no generation file ({'; '.join(reasons)})")
    raise CorruptFileError(f"{path}: no good generation ({'; '.join(reasons)})")
