"""Shared test fixtures: where the real data lives, and markers that skip cleanly."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from fake_clock import FakeClock

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
KITCHEN = SHARED_DATA / "7scenes-kitchen-0-299"
# Torch threads per test: 1 unless OMP_NUM_THREADS says otherwise, so that running the suite
# under `OMP_NUM_THREADS=2` really changes the reduction order (docs/testing.md).
TORCH_THREADS = int(os.environ.get("OMP_NUM_THREADS") or 1)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "loopback: real processes over Zenoh TCP on 127.0.0.1")
    # The field's tensors are small: on a 2-core machine one torch thread is several times
    # faster than two (measured; see docs/architecture.md), and tests then run alike in CI.
    try:
        import torch

        torch.set_num_threads(TORCH_THREADS)
    except ImportError:  # pragma: no cover
        pass


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skip_gpu = None
    try:
        import torch

        if not torch.cuda.is_available():
            skip_gpu = pytest.mark.skip(reason="needs CUDA; none available")
    except ImportError:
        skip_gpu = pytest.mark.skip(reason="needs torch with CUDA")
    skip_data = pytest.mark.skip(reason=f"real data not found at {KITCHEN}")
    for item in items:
        if "gpu" in item.keywords and skip_gpu is not None:
            item.add_marker(skip_gpu)
        if "data" in item.keywords and not KITCHEN.is_dir():
            item.add_marker(skip_data)


@pytest.fixture(autouse=True)
def _torch_threads():
    """Every test starts with TORCH_THREADS torch threads, whatever an earlier
    in-process command set, and leaves torch's deterministic-algorithms setting (which
    in-process daemon commands switch on through run.deterministic) as it found it."""
    try:
        import torch
    except ImportError:  # pragma: no cover
        yield
        return
    deterministic = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(TORCH_THREADS)
    yield
    torch.set_num_threads(TORCH_THREADS)
    torch.use_deterministic_algorithms(deterministic, warn_only=warn_only)


@pytest.fixture(scope="session")
def kitchen_path() -> Path:
    """The first 300 frames of 7-Scenes red kitchen (skips when absent)."""
    if not KITCHEN.is_dir():
        pytest.skip(f"real data not found at {KITCHEN}")
    return KITCHEN


@pytest.fixture
def fake_clock() -> FakeClock:
    """A clock that only moves when the test moves it (pass it where code takes `clock`/`now`)."""
    return FakeClock()


@pytest.fixture
def renamed(monkeypatch) -> list[Path]:
    """Every destination `os.replace` renames a file to during the test, in order (atomic
    writes end in one)."""
    done: list[Path] = []
    real_replace = os.replace

    def replace(src, dst) -> None:
        done.append(Path(dst))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    return done
