"""The configuration tree: presets, source order, errors, round trip, generated docs."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel, ValidationError

from cpslam.common import config as config_pkg
from cpslam.common.config import (
    ConfigError,
    CpslamConfig,
    available_presets,
    config_from_cli,
    config_reference_markdown,
    config_to_dict,
    load_config,
    load_config_file,
    override_config,
    preset_text,
    save_config,
)
from cpslam.common.config import loader as loader_mod
from cpslam.common.config.reference import preset_comments
from cpslam.common.field_config import field_spec

REPO_ROOT = Path(__file__).resolve().parents[2]

# DESIGN §1: the paper's numbers, which the `paper` preset must reproduce exactly.
PAPER = {
    "field.patch_size": 4,
    "field.feature_dim": 32,
    "field.grid_size": 0.14,
    "field.n_near": 16,
    "field.near_lo": 0.95,
    "field.near_hi": 1.05,
    "field.n_uniform": 4,
    "field.far_hi": 1.05,
    "field.no_depth_near": 0.001,
    "field.k_neighbors": 8,
    "field.radius": 0.15,
    "field.pe_feature_order": 1,
    "field.pe_offset_order": 7,
    "field.c_hidden": 256,
    "field.c_layers": 1,
    "field.u_hidden": 128,
    "field.u_layers": 2,
    "field.g_hidden": 256,
    "field.g_layers": 1,
    "field.leaky_slope": 0.01,
    "tracking.n_pixels": 1500,
    "tracking.lr": 0.0015,
    "tracking.init": "zero_motion",
    "tracking.color_weight": 0.0,
    "tracking.outlier_err_lo": 0.1,
    "tracking.outlier_err_hi": 10.0,
    "tracking.outlier_var_factor": 2.0,
    "mapping.every": 10,
    "mapping.n_pixels": 3000,
    "mapping.n_pixels_first": 3136,
    "mapping.iters_first": 3000,
    "mapping.iters": 200,
    "mapping.iters_after_fusion": 150,
    "mapping.covisible_keyframes": 5,
    "mapping.color_weight": 0.2,
    "mapping.lr_decoders": 0.003,
    "mapping.lr_features": 0.005,
    "mapping.feature_lr_decay": 0.1,
    "mapping.feature_lr_decay_steps": 10000,
    "keyframes.every": 50,
    "place_recognition.aggregation": "netvlad",
    # Where the paper is silent, the official code's values.
    "field.c_out": 128,
    "keyframes.image_downscale": 1,
    "loop.lambda_fine": 0.88,
    "loop.lambda_coarse": 0.80,
    "loop.coarse_method": "none",
    "pose_graph.robust_kernel": "none",
    "federation.weighting": "uniform",
}


def _get(cfg: CpslamConfig, dotted: str) -> object:
    value: object = cfg
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def _models(model: type[BaseModel]) -> list[type[BaseModel]]:
    out = [model]
    for info in model.model_fields.values():
        if isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel):
            out += _models(info.annotation)
    return out


@pytest.mark.parametrize("name", ["paper", "gpu", "cpu", "tiny"])
def test_every_preset_loads(name: str) -> None:
    assert name in available_presets()
    cfg = load_config(name, env={})
    assert isinstance(cfg, CpslamConfig)


def test_paper_preset_is_the_paper() -> None:
    cfg = load_config("paper", env={})
    wrong = {k: (_get(cfg, k), v) for k, v in PAPER.items() if _get(cfg, k) != v}
    assert not wrong, wrong
    # The decoder input sizes DESIGN quotes: PE_1 of a 32-d feature and PE_7 of a 3-d offset.
    f = cfg.field
    assert f.feature_dim * (1 + 2 * f.pe_feature_order) == 96
    assert 3 * (1 + 2 * f.pe_offset_order) == 45
    # The paper's decoder size: 1.36e5 parameters.
    decoders = field_spec(f).decoders(seed=0)
    assert round(sum(p.numel() for p in decoders.parameters()), -3) == 136_000


def test_gpu_preset_is_the_defaults() -> None:
    assert load_config("gpu", env={}) == CpslamConfig()


def test_every_paper_difference_has_a_reason() -> None:
    """Each line of paper.yaml says why the default differs; docs/configuration.md tables it."""
    text = preset_text("paper")
    reasons = preset_comments(text)
    changes = load_config("paper", env={}).model_dump(mode="json")
    defaults = CpslamConfig().model_dump(mode="json")
    changed = {f"{sec}.{k}" for sec in defaults for k in defaults[sec]
               if changes[sec][k] != defaults[sec][k]}
    assert changed == set(reasons), "a paper.yaml key without a reason, or a reason without key"
    assert all(len(reason) > 10 for reason in reasons.values()), reasons


def test_cpu_preset_is_smaller_and_halves_vga() -> None:
    cpu, paper = load_config("cpu", env={}), load_config("paper", env={})
    assert round(640 * cpu.camera.downscale) == 320 and round(480 * cpu.camera.downscale) == 240
    assert cpu.field.c_hidden < paper.field.c_hidden
    assert cpu.tracking.iters < paper.tracking.iters
    assert cpu.mapping.iters_first < paper.mapping.iters_first


def test_source_order_preset_file_env_set(tmp_path: Path) -> None:
    file = tmp_path / "c.yaml"
    file.write_text("tracking:\n  iters: 40\n  n_pixels: 41\n")
    env = {"CPSLAM_TRACKING__ITERS": "50", "CPSLAM_TRACKING__LR": "0.01"}
    assert load_config("cpu", env={}).tracking.iters == 4  # the preset's own value
    assert load_config("cpu", file, env={}).tracking.iters == 40
    assert load_config("cpu", file, env=env).tracking.iters == 50
    cfg = load_config("cpu", file, ["tracking.iters=60"], env=env)
    assert cfg.tracking.iters == 60
    # Deep merge: what later sources leave alone survives from earlier ones.
    assert cfg.tracking.n_pixels == 41 and cfg.tracking.lr == 0.01
    assert cfg.field.c_hidden == 32


def test_environment_defaults_to_os_environ(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CPSLAM_LOOP__LAMBDA_FINE", "0.95")
    monkeypatch.setenv("CPSLAM_HOME", "/somewhere")  # no "__": not configuration
    assert load_config("paper").loop.lambda_fine == 0.95


def test_unknown_key_in_preset(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(loader_mod, "preset_text", lambda name: "tracking:\n  iterz: 3\n")
    with pytest.raises(ConfigError, match=r"preset 'cpu'.*'tracking\.iterz'.*iters, n_pixels"):
        load_config("cpu", env={})


def test_unknown_key_in_file(tmp_path: Path) -> None:
    file = tmp_path / "bad.yaml"
    file.write_text("mapping:\n  itters: 3\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*'mapping\.itters'.*valid keys"):
        load_config("cpu", file, env={})


def test_unknown_section_in_file_lists_sections(tmp_path: Path) -> None:
    file = tmp_path / "bad.yaml"
    file.write_text("traking:\n  iters: 3\n")
    with pytest.raises(ConfigError, match=r"'traking'.*camera, field, tracking"):
        load_config("cpu", file, env={})


def test_unknown_key_in_env() -> None:
    with pytest.raises(ConfigError, match=r"CPSLAM_LOOP__LAMBDA_FIN.*'loop\.lambda_fin'"):
        load_config("cpu", env={"CPSLAM_LOOP__LAMBDA_FIN": "0.9"})


def test_unknown_key_in_set() -> None:
    with pytest.raises(ConfigError, match=r"--set loop\.lamda=1.*'loop\.lamda'.*lambda_fine"):
        load_config("cpu", overrides=["loop.lamda=1"], env={})


@pytest.mark.parametrize("item", ["loop.lambda_fine", "=3", "loop..x=3"])
def test_malformed_set_item(item: str) -> None:
    with pytest.raises(ConfigError, match="--set"):
        load_config("cpu", overrides=[item], env={})


def test_set_below_a_value_is_an_error() -> None:
    with pytest.raises(ConfigError, match=r"'tracking\.iters' is a value, not a section"):
        load_config("cpu", overrides=["tracking.iters.x=1"], env={})


def test_wrong_type_names_key_and_source(tmp_path: Path) -> None:
    file = tmp_path / "c.yaml"
    file.write_text("tracking:\n  iters: many\n")
    with pytest.raises(ConfigError) as info:
        load_config("cpu", file, env={})
    message = str(info.value)
    assert "tracking.iters = 'many'" in message and str(file) in message
    with pytest.raises(ConfigError, match=r"field\.k_neighbors.*--set field\.k_neighbors=0"):
        load_config("cpu", overrides=["field.k_neighbors=0"], env={})


def test_bad_enum_lists_choices() -> None:
    with pytest.raises(ConfigError, match=r"loop\.coarse_method.*'icp' or 'none'"):
        load_config("cpu", overrides=["loop.coarse_method=sift"], env={})
    with pytest.raises(ConfigError, match=r"CPSLAM_FIELD__NEIGHBOUR_BACKEND.*'auto', 'kdtree'"):
        load_config("cpu", env={"CPSLAM_FIELD__NEIGHBOUR_BACKEND": "faiss"})


@pytest.mark.parametrize(
    ("item", "pattern"),
    [
        ("loop.lambda_fine=0.5", r"lambda_fine \(0\.5\) must be at least lambda_coarse"),
        ("field.near_lo=1.2", r"near_lo \(1\.2\) must be below near_hi"),
        ("camera.depth_min=20", r"depth_min \(20\.0\) must be below depth_max"),
        ("camera.fx=500", r"all of fx, fy, cx, cy, width, height or none"),
        ("tracking.outlier_err_lo=20", r"outlier_err_lo .* must be below outlier_err_hi"),
        ("run.device=gpu", r"expected auto, cpu, cuda or cuda:N"),
        ("run.name=a/b", r"one path component"),
        ("transport.session=a/b", r"session 'a/b'"),
        ("transport.listen=[http://x:1]", r"should look like tcp/HOST:PORT"),
        ("transport.connect=[tcp/1.2.3.4:70000]", r"port must be at most 65535"),
        ("camera.downscale=2", r"camera\.downscale"),
        ("link.depth_step_mm_per_m2=0.05", r"expected 0 \(linear mm\) or 0\.1-50"),
    ],
)
def test_cross_field_and_format_checks(item: str, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        load_config("paper", overrides=[item], env={})


def test_set_values_are_yaml() -> None:
    cfg = load_config(
        "paper",
        overrides=[
            "transport.listen=[tcp/0.0.0.0:7447, udp/[::1]:7448]",
            "run.name=2024",  # a text field keeps text that YAML would read as a number
            "place_recognition.weights=/data/netvlad.pt",
            "camera.depth_scale=null",
            "tracking.keep_best=false",
            "pose_graph.rel_tol=1e-6",
        ],
        env={"CPSLAM_TRANSPORT__CONNECT": "tcp/10.0.0.2:7447,unixsock-stream/tmp/z.sock"},
    )
    assert cfg.transport.listen == ["tcp/0.0.0.0:7447", "udp/[::1]:7448"]
    assert cfg.transport.connect == ["tcp/10.0.0.2:7447", "unixsock-stream/tmp/z.sock"]
    assert cfg.run.name == "2024"
    assert cfg.place_recognition.weights == Path("/data/netvlad.pt")
    assert cfg.camera.depth_scale is None and cfg.tracking.keep_best is False
    assert cfg.pose_graph.rel_tol == 1e-6


def test_config_is_read_only() -> None:
    cfg = load_config("tiny", env={})
    with pytest.raises(ValidationError):
        cfg.tracking.iters = 3  # type: ignore[misc]
    assert override_config(cfg, ["tracking.iters=3"]).tracking.iters == 3
    assert cfg.tracking.iters != 3


def test_unknown_preset_lists_available() -> None:
    with pytest.raises(ConfigError, match="unknown preset 'gpus'; available presets: cpu, gpu"):
        load_config("gpus", env={})


def test_unreadable_and_non_mapping_files(tmp_path: Path) -> None:
    missing = tmp_path / "missing.yaml"
    with pytest.raises(ConfigError, match=rf"cannot read config file {missing}"):
        load_config("cpu", missing, env={})
    listing = tmp_path / "list.yaml"
    listing.write_text("- tracking\n- mapping\n")
    with pytest.raises(ConfigError, match=r"list\.yaml must hold a mapping.*got a list"):
        load_config("cpu", listing, env={})
    broken = tmp_path / "broken.yaml"
    broken.write_text("tracking: [1,\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml is not valid YAML at line"):
        load_config("cpu", broken, env={})
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing\nmapping:\n")
    assert load_config("cpu", empty, env={}) == load_config("cpu", env={})


@pytest.mark.parametrize("name", ["paper", "gpu", "cpu", "tiny"])
def test_save_load_round_trip(tmp_path: Path, name: str) -> None:
    cfg = load_config(
        name,
        overrides=[
            "place_recognition.weights=w/netvlad.pt",
            "transport.listen=[tcp/0.0.0.0:7447]",
            "camera.fx=525.5",
            "camera.fy=525.0",
            "camera.cx=319.5",
            "camera.cy=239.5",
            "camera.width=640",
            "camera.height=480",
            "run.name=exp1",
        ],
        env={},
    )
    path = tmp_path / "sub" / "config.yaml"
    save_config(cfg, path)
    plain = yaml.safe_load(path.read_text())  # no Python tags: Paths and tuples are plain
    assert plain == config_to_dict(cfg)
    assert plain["place_recognition"]["weights"] == "w/netvlad.pt"
    assert load_config_file(path) == cfg


def test_config_from_cli_flags_win() -> None:
    cfg = config_from_cli(
        "tiny", None, ["run.device=cuda", "run.seed=1"], device="cpu", seed=7, env={}
    )
    assert (cfg.run.device, cfg.run.seed) == ("cpu", 7)
    assert config_from_cli("tiny", None, ["run.seed=1"], env={}).run.seed == 1
    with pytest.raises(ConfigError, match=r"run\.device = 'tpu' \(from --device\)"):
        config_from_cli("tiny", None, [], device="tpu", env={})


def test_every_field_has_a_one_line_description() -> None:
    models = _models(CpslamConfig)
    assert len(models) == 1 + len(CpslamConfig.model_fields)
    for model in models:
        assert model.__doc__, model.__name__
        assert model.model_config.get("extra") == "forbid", model.__name__
        for name, info in model.model_fields.items():
            text = info.description or ""
            assert text.strip(), f"{model.__name__}.{name} has no description"
            assert "\n" not in text, f"{model.__name__}.{name}: description spans lines"


def test_reference_doc_is_up_to_date() -> None:
    doc = REPO_ROOT / "docs" / "configuration.md"
    expected = config_reference_markdown()
    assert doc.read_text(encoding="utf-8") == expected, (
        "docs/configuration.md is stale: python -m cpslam.common.config > docs/configuration.md"
    )
    # Every dotted key appears in the reference.
    for section, info in CpslamConfig.model_fields.items():
        for field in info.annotation.model_fields:  # type: ignore[union-attr]
            assert f"`{section}.{field}`" in expected


def test_public_api_is_exported() -> None:
    for name in config_pkg.__all__:
        assert hasattr(config_pkg, name), name
