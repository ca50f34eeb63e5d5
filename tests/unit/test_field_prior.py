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
    with pytest.raises(ValueError, match=r"does not fit the decoders .*missing"):
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
    cpu = field_spec(load_config("cpu", overrides=["field.prior=cpu.npz"], env={}).field)
    arrays = load_prior(resolve_prior(cpu.prior))
    decoders = cpu.decoders(seed=0)
    for key, value in decoders.state_dict().items():
        assert np.array_equal(value.numpy(), arrays[f"decoders.{key}"])
    assert not _same(decoders, replace(cpu, prior=None).decoders(seed=0))


def test_cpslam_prior_fits_the_same_file_twice_and_the_file_loads(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from cpslam.cli import app

    args = ["prior", "--preset", "tiny", "--scenes", "2", "--num-frames", "3",
            "--set", "mapping.iters_first=20", "--set", "mapping.iters=5"]
    first, second = tmp_path / "a.npz", tmp_path / "b.npz"
    for out in (first, second):
        result = CliRunner().invoke(app, [*args, str(out)])
        assert result.exit_code == 0, result.output
    a, b = load_prior(first), load_prior(second)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    tiny = spec("tiny")
    fitted = replace(tiny, prior=str(first)).decoders(seed=0)
    assert not _same(fitted, tiny.decoders(seed=0))  # fitted, not the random start
    assert _same(replace(tiny, prior=str(first)).cnn(seed=7), tiny.cnn(seed=0))
    again = CliRunner().invoke(app, [*args, str(first)])
    assert again.exit_code == 2 and "already exists" in again.output
    wrong = CliRunner().invoke(app, [*args, str(tmp_path / "p.pt")])
    assert wrong.exit_code == 2 and "must end in .npz" in wrong.output


def test_the_config_refuses_a_prior_that_is_not_an_npz() -> None:
    with pytest.raises(ValueError, match=r"prior must name an \.npz file"):
        load_config("tiny", overrides=["field.prior=weights.pt"], env={})
    assert load_config("cpu", overrides=["field.prior=null"], env={}).field.prior is None
