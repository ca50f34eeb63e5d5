"""Decoder priors: saved and loaded whole, refused with a clear error when they do not fit."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from cpslam.common.config import load_config
from cpslam.common.field.prior import BUNDLED, load_prior, resolve_prior, save_prior
from cpslam.common.field_config import field_spec
from tests.unit.spec_helpers import spec


def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_a_prior_gives_every_seed_its_decoders_and_cnn(tmp_path: Path) -> None:
    tiny = spec("tiny")
    path = tmp_path / "p.npz"
    save_prior(path, tiny.decoders(seed=1), tiny.cnn(seed=1))
    with_prior = replace(tiny, prior=str(path))
    assert _same(with_prior.decoders(seed=5), tiny.decoders(seed=1))
    assert _same(with_prior.cnn(seed=5), tiny.cnn(seed=1))
    assert not _same(tiny.decoders(seed=5), tiny.decoders(seed=1))  # the test can fail
    # A file rewritten in place is read again, not served from the cache.
    save_prior(path, tiny.decoders(seed=2), tiny.cnn(seed=2))
    assert _same(with_prior.decoders(seed=5), tiny.decoders(seed=2))


def test_a_prior_of_other_widths_is_refused(tmp_path: Path) -> None:
    tiny = spec("tiny")
    path = tmp_path / "p.npz"
    save_prior(path, tiny.decoders(seed=1), tiny.cnn(seed=1))
    wider = replace(tiny, c_hidden=tiny.c_hidden * 2, prior=str(path))
    with pytest.raises(ValueError, match=r"field\.prior: .*p\.npz: decoders\.c_feature\.weight "
                                         r"has shape"):
        wider.decoders(seed=0)
    deeper = replace(tiny, u_layers=tiny.u_layers + 1, prior=str(path))
    with pytest.raises(ValueError, match=r"does not fit these decoders .*missing"):
        deeper.decoders(seed=0)


def test_a_missing_or_foreign_file_names_the_field(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"field\.prior: no file .*nowhere\.npz "
                                                r"\(bundled priors: cpu\.npz"):
        resolve_prior("nowhere.npz")
    assert resolve_prior("cpu.npz") == BUNDLED / "cpu.npz"
    pickled = tmp_path / "objects.npz"
    np.savez(pickled, a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(ValueError, match=r"objects\.npz is not a prior"):
        load_prior(pickled)
    doubles = tmp_path / "doubles.npz"
    np.savez(doubles, a=np.zeros(3))
    with pytest.raises(ValueError, match=r"doubles\.npz: a is float64, expected float32"):
        load_prior(doubles)


def test_the_bundled_cpu_prior_fits_the_cpu_preset() -> None:
    cpu = field_spec(load_config("cpu", env={}).field)
    assert cpu.prior == "cpu.npz"
    arrays = load_prior(resolve_prior(cpu.prior))
    decoders = cpu.decoders(seed=0)
    for key, value in decoders.state_dict().items():
        assert np.array_equal(value.numpy(), arrays[f"decoders.{key}"])
    assert not _same(decoders, replace(cpu, prior=None).decoders(seed=0))
