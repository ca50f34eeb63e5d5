"""`cpslam eval ate` with several --gt/--est pairs: one alignment for all, checked against an
alignment computed here by hand (Kabsch on the pooled positions) for a known transform."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.geometry import se3_exp
from cpslam.common.trajectory import read_tum, write_tum
from cpslam.tools.eval.cli import ate

T_GT_EST = se3_exp(np.array([0.4, -1.0, 0.25, 0.1, 0.7, -0.3]))  # est frame -> gt frame
OFFSET = np.array([0.05, -0.02, 0.0])  # agent 1's estimate is off by this (est frame)


@pytest.fixture
def app() -> typer.Typer:
    app = typer.Typer()
    app.command()(ate)
    return app


def _pairs(tmp_path: Path, offset: np.ndarray) -> tuple[list[str], list[tuple]]:
    """Two agents' gt.tum and est.tum (est = inv(T_GT_EST) gt, agent 1 shifted by
    `offset`); the command's arguments and the (gt, est) positions."""
    args, xyz = [], []
    for a in (0, 1):
        n = 40 + 10 * a
        s = np.linspace(0, 1, n)
        xi = np.zeros((n, 6))
        xi[:, 0] = 2.0 * s + a
        xi[:, 1] = np.sin(3 * s + a)
        xi[:, 2] = 0.5 * s**2 - a
        xi[:, 4] = s
        gt = se3_exp(xi)
        est = np.linalg.inv(T_GT_EST)[None] @ gt
        if a == 1:
            est[:, :3, 3] += offset
        stamps = 100.0 * a + np.arange(n) / 30.0
        write_tum(tmp_path / f"gt{a}.tum", stamps, gt)
        write_tum(tmp_path / f"est{a}.tum", stamps, est)
        args += ["--gt", str(tmp_path / f"gt{a}.tum"), "--est", str(tmp_path / f"est{a}.tum")]
        # As written: the files round the positions.
        xyz.append(tuple(read_tum(tmp_path / f"{k}{a}.tum")[1][:, :3, 3] for k in ("gt", "est")))
    return args, xyz


def _kabsch(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |R est + t - gt|^2 (written out here, not cpslam's umeyama)."""
    mu_e, mu_g = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - mu_g).T @ (est - mu_e))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return R, mu_g - R @ mu_e


def _run(app: typer.Typer, args: list[str]) -> dict:
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def test_exact_estimates_recover_the_transform(tmp_path: Path, app: typer.Typer) -> None:
    args, _ = _pairs(tmp_path, np.zeros(3))
    record = _run(app, args)
    assert record["schema_version"] == 1 and record["align"] == "se3"
    np.testing.assert_allclose(record["joint"]["T_gt_est"], T_GT_EST, atol=1e-6)
    assert record["joint"]["rmse_m"] < 1e-6
    assert [p["n_pairs"] for p in record["pairs"]] == [40, 50]


def test_joint_figure_matches_a_hand_computed_alignment(tmp_path: Path,
                                                        app: typer.Typer) -> None:
    args, xyz = _pairs(tmp_path, OFFSET)
    record = _run(app, args)
    R, t = _kabsch(np.concatenate([e for _, e in xyz]), np.concatenate([g for g, _ in xyz]))
    errors = [np.linalg.norm(e @ R.T + t - g, axis=1) for g, e in xyz]
    np.testing.assert_allclose(np.asarray(record["joint"]["T_gt_est"])[:3, :3], R, atol=1e-9)
    np.testing.assert_allclose(np.asarray(record["joint"]["T_gt_est"])[:3, 3], t, atol=1e-9)
    joint = np.sqrt(np.mean(np.concatenate(errors) ** 2))
    assert record["joint"]["rmse_m"] == pytest.approx(joint, rel=1e-9)
    for part, err in zip(record["pairs"], errors, strict=True):
        assert part["rmse_m"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-9)
    # The offset between the agents shows only under one alignment: alone, agent 1's own
    # fit absorbs it.
    alone = _run(app, [*args[4:], "--align", "se3"])
    assert alone["rmse_m"] < 1e-6 < 0.01 < record["pairs"][1]["rmse_m"]
    text = CliRunner().invoke(app, args).output
    assert "2 pairs under one se3 alignment" in text and "joint" in text
    assert f"{100 * joint:.2f}" in text


def test_pairs_must_match_and_single_pair_options_refused(tmp_path: Path,
                                                          app: typer.Typer) -> None:
    args, _ = _pairs(tmp_path, OFFSET)
    result = CliRunner().invoke(app, args[:-2])
    assert result.exit_code == 2 and "2 --gt and 1 --est" in result.output
    result = CliRunner().invoke(app, [*args, "--rpe", "1"])
    assert result.exit_code == 2 and "one --gt/--est pair" in result.output
    plot = tmp_path / "joint.png"
    result = CliRunner().invoke(app, [*args, "--plot", str(plot), "--out",
                                      str(tmp_path / "joint.json")])
    assert result.exit_code == 0, result.output
    assert plot.read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "joint.json").read_text())["joint"]["n_pairs"] == 90
