"""`cpslam.common.durable`: atomic writes, sealed generations, fallback to the previous one."""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path

import pytest
import torch

from cpslam.common import durable


def _count_fsyncs(monkeypatch) -> list[int]:
    """Record the file descriptors os.fsync is called with (the real fsync still runs)."""
    calls: list[int] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        calls.append(fd)
        real(fd)

    monkeypatch.setattr(durable.os, "fsync", fsync)
    return calls


def test_atomic_text_round_trip_fsyncs_the_file_and_the_folder(tmp_path: Path, monkeypatch) -> None:
    calls = _count_fsyncs(monkeypatch)
    folders: list[Path] = []
    real_fsync_dir = durable.fsync_dir
    monkeypatch.setattr(
        durable, "fsync_dir", lambda folder: (folders.append(Path(folder)), real_fsync_dir(folder))
    )
    path = durable.write_text_atomic(tmp_path / "sub" / "a.json", '{"x": 1}\n')
    assert path.read_text() == '{"x": 1}\n'
    assert folders == [tmp_path / "sub"]
    assert len(calls) == 2, "one fsync for the file, one for its folder"
    assert os.listdir(tmp_path / "sub") == ["a.json"], "no temporary file left behind"


def test_a_failed_atomic_write_keeps_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = durable.write_text_atomic(tmp_path / "m.json", "old\n")
    with pytest.raises(RuntimeError), durable.atomic_open(path, "w") as f:
        f.write("half of the new")
        raise RuntimeError("crash in the middle of the write")
    assert path.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["m.json"]


def test_a_full_disk_raises_and_leaves_the_target_untouched(tmp_path: Path, monkeypatch) -> None:
    path = durable.write_bytes_atomic(tmp_path / "s.bin", b"good")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(durable.os, "fsync", full)
    with pytest.raises(OSError) as err:
        durable.write_bytes_atomic(path, b"new")
    assert err.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"good"
    assert os.listdir(tmp_path) == ["s.bin"]


def test_torch_save_atomic_round_trip(tmp_path: Path) -> None:
    state = {"w": torch.arange(6.0).reshape(2, 3), "n": 3}
    path = durable.torch_save_atomic(state, tmp_path / "d.pt")
    loaded = torch.load(path, weights_only=True)
    assert torch.equal(loaded["w"], state["w"]) and loaded["n"] == 3


def test_generations_round_trip_and_keep_the_previous(tmp_path: Path) -> None:
    path = tmp_path / "state.pt"
    durable.save_generation(path, b"first")
    durable.save_generation(path, b"second")
    newest, prev = durable.generation_paths(path)
    assert prev.name == "state.pt.prev"
    assert durable.unseal(prev.read_bytes()) == b"first"
    assert durable.load_generation(path, bytes) == (b"second", newest)
    assert durable.has_generation(path)
    assert sorted(os.listdir(tmp_path)) == ["state.pt", "state.pt.prev"]


def test_a_torn_newest_generation_falls_back_to_the_previous(tmp_path: Path, caplog) -> None:
    path = tmp_path / "state.pt"
    durable.save_generation(path, b"A" * 1000)
    durable.save_generation(path, b"B" * 1000)
    path.write_bytes(path.read_bytes()[:700])  # the newest cut short, as by a crash
    with caplog.at_level(logging.WARNING, logger="cpslam.common.durable"):
        payload, used = durable.load_generation(path, bytes)
    assert payload == b"A" * 1000
    assert used == tmp_path / "state.pt.prev"
    assert str(path) in caplog.text and "trailer" in caplog.text
    # The torn file is set aside, so the next generation does not rotate it over the good one.
    assert (tmp_path / "state.pt.corrupt").is_file() and not path.exists()
    durable.save_generation(path, b"C" * 10)
    assert durable.unseal((tmp_path / "state.pt.prev").read_bytes()) == b"A" * 1000


def test_a_corrupt_payload_is_detected_by_the_trailer(tmp_path: Path) -> None:
    path = durable.save_generation(tmp_path / "state.pt", b"payload bytes")
    blob = bytearray(path.read_bytes())
    blob[3] ^= 0xFF  # one flipped bit pattern inside the payload, the trailer intact
    with pytest.raises(durable.CorruptFileError, match="SHA-256"):
        durable.unseal(bytes(blob), path)
    path.write_bytes(bytes(blob))
    with pytest.raises(durable.CorruptFileError, match=r"state\.pt"):
        durable.load_generation(path, bytes)  # no previous generation to fall back to


def test_a_payload_that_does_not_decode_falls_back(tmp_path: Path) -> None:
    path = tmp_path / "state.pt"
    durable.save_generation(path, durable.torch_bytes({"v": 1}))
    durable.save_generation(path, b"sealed but not a torch file")
    state, used = durable.load_generation(path, lambda b: torch.load(_buf(b), weights_only=True))
    assert state == {"v": 1} and used.name == "state.pt.prev"


def test_a_missing_newest_generation_uses_the_previous_and_none_raises(tmp_path: Path) -> None:
    path = tmp_path / "state.pt"
    with pytest.raises(FileNotFoundError, match="no generation"):
        durable.load_generation(path, bytes)
    durable.save_generation(path, b"one")
    os.replace(path, tmp_path / "state.pt.prev")  # a crash between the two renames
    assert durable.load_generation(path, bytes)[0] == b"one"


def test_a_length_mismatch_is_reported(tmp_path: Path) -> None:
    sealed = durable.seal(b"abc")
    with pytest.raises(durable.CorruptFileError, match="payload bytes"):
        durable.unseal(b"x" + sealed, "f")
    with pytest.raises(durable.CorruptFileError, match="shorter"):
        durable.unseal(b"short", "f")


def _buf(data: bytes):
    import io

    return io.BytesIO(data)
