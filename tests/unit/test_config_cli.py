import typer
import yaml
from typer.testing import CliRunner

from cpslam.common.config import load_config
from cpslam.common.config.cli import presets, show

app = typer.Typer()
app.command("show")(show)
app.command("presets")(presets)
runner = CliRunner()


def test_show_prints_the_effective_config() -> None:
    result = runner.invoke(app, ["show", "-p", "tiny", "--set", "tracking.iters=7"])
    assert result.exit_code == 0, result.output
    data = yaml.safe_load(result.output)
    assert data["tracking"]["iters"] == 7
    assert data["field"] == yaml.safe_load(
        yaml.safe_dump(load_config("tiny", env={}).field.model_dump(mode="json"))
    )


def test_show_reports_unknown_keys_with_exit_2() -> None:
    result = runner.invoke(app, ["show", "--set", "tracking.bogus=7"])
    assert result.exit_code == 2
    assert "tracking.bogus" in result.output


def test_presets_lists_all() -> None:
    result = runner.invoke(app, ["presets"])
    assert result.exit_code == 0
    for name in ("paper", "cpu", "tiny"):
        assert f"--- {name} ---" in result.output
