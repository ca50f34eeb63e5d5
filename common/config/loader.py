"""Building a `CpslamConfig` from a preset, a YAML file, the environment and `--set` items.

Sources apply in order, later wins: preset -> config file -> `CPSLAM_<SECTION>__<FIELD>`
environment variables -> `--set section.field=value` items. They are deep-merged as plain
dicts and validated once; every error names the source and the dotted key.
"""

from __future__ import annotations

import logging
import os
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from cpslam.common.config.schema import CpslamConfig

__all__ = [
    "ConfigError",
    "available_presets",
    "config_from_cli",
    "config_to_dict",
    "load_config",
    "load_config_file",
    "override_config",
    "preset_text",
    "save_config",
]

logger = logging.getLogger(__name__)

ENV_PREFIX = "CPSLAM_"
_ENV_SEP = "__"


class ConfigError(ValueError):
    """A configuration source holds an unknown key, a bad value or is unreadable."""


def load_config(
    preset: str = "cpu",
    config_file: Path | str | None = None,
    overrides: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
) -> CpslamConfig:
    """Build the effective configuration.

    `env=None` reads `os.environ`; pass `{}` to ignore the environment.
    """
    return _build(_source_layers(preset, config_file, overrides, env))


def config_from_cli(
    preset: str,
    config_file: Path | str | None,
    sets: Sequence[str],
    device: str | None = None,
    seed: int | None = None,
    env: Mapping[str, str] | None = None,
) -> CpslamConfig:
    """`load_config` for daemons: `--device` and `--seed` flags override the run section."""
    layers = _source_layers(preset, config_file, sets, env)
    if device is not None:
        layers.append(_Layer("--device", {"run": {"device": device}}))
    if seed is not None:
        layers.append(_Layer("--seed", {"run": {"seed": seed}}))
    return _build(layers)


def override_config(cfg: CpslamConfig, sets: Sequence[str]) -> CpslamConfig:
    """A copy of `cfg` with `section.field=value` items applied and validated."""
    return _build([_Layer("base config", config_to_dict(cfg))] + [_set_layer(s) for s in sets])


def load_config_file(path: Path | str) -> CpslamConfig:
    """Read a config file over the defaults (no preset); reads `save_config` output exactly."""
    return _build([_file_layer(Path(path))])


def save_config(cfg: CpslamConfig, path: Path | str) -> None:
    """Write `cfg` as YAML (paths as strings, tuples as lists), creating parent folders."""
    from cpslam.common.durable import write_text_atomic

    text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=False)
    write_text_atomic(path, "# cpslam effective configuration\n" + text)


def config_to_dict(cfg: CpslamConfig) -> dict[str, Any]:
    """Plain nested dict of YAML/JSON-safe values."""
    return cfg.model_dump(mode="json")


def available_presets() -> list[str]:
    """Names of the presets shipped with the package."""
    folder = resources.files(__package__) / "presets"
    return sorted(p.name[: -len(".yaml")] for p in folder.iterdir() if p.name.endswith(".yaml"))


def preset_text(name: str) -> str:
    """The YAML text of a shipped preset."""
    names = available_presets()
    if name not in names:
        raise ConfigError(f"unknown preset {name!r}; available presets: {', '.join(names)}")
    return (resources.files(__package__) / "presets" / f"{name}.yaml").read_text("utf-8")


@dataclass
class _Layer:
    """One source's partial config and the label errors name it by."""

    label: str
    data: dict[str, Any]


def _source_layers(
    preset: str,
    config_file: Path | str | None,
    sets: Sequence[str],
    env: Mapping[str, str] | None,
) -> list[_Layer]:
    layers = [_preset_layer(preset)]
    if config_file is not None:
        layers.append(_file_layer(Path(config_file)))
    layers.extend(_env_layers(os.environ if env is None else env))
    layers.extend(_set_layer(item) for item in sets)
    return layers


def _preset_layer(name: str) -> _Layer:
    label = f"preset {name!r}"
    return _Layer(label, _parse_yaml_mapping(preset_text(name), label))


def _file_layer(path: Path) -> _Layer:
    label = f"config file {path}"
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read {label}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"cannot read {label}: not UTF-8 text ({exc.reason})") from exc
    return _Layer(label, _parse_yaml_mapping(text, label))


def _parse_yaml_mapping(text: str, label: str) -> dict[str, Any]:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = ""
        mark = getattr(exc, "problem_mark", None)
        if mark is not None:
            where = f" at line {mark.line + 1}, column {mark.column + 1}"
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{label} is not valid YAML{where}: {problem}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{label} must hold a mapping of sections (e.g. 'tracking: {{iters: 50}}'), "
            f"got a {type(data).__name__}"
        )
    return data


def _env_layers(env: Mapping[str, str]) -> list[_Layer]:
    layers = []
    # Sorted so that a run does not depend on the environment's ordering.
    for name in sorted(env):
        if not name.startswith(ENV_PREFIX) or _ENV_SEP not in name:
            continue
        path = name[len(ENV_PREFIX) :].lower().split(_ENV_SEP)
        label = f"environment variable {name}"
        if any(not part for part in path):
            raise ConfigError(f"{label}: expected CPSLAM_<SECTION>__<FIELD>, got an empty part")
        layers.append(_Layer(label, _nest(path, _parse_value(env[name], path, label))))
    return layers


def _set_layer(item: str) -> _Layer:
    label = f"--set {item}"
    key, sep, raw = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"{label}: expected section.field=value, e.g. loop.lambda_fine=0.85")
    path = key.split(".")
    if any(not part for part in path):
        raise ConfigError(f"{label}: key {key!r} has an empty part")
    return _Layer(label, _nest(path, _parse_value(raw.strip(), path, label)))


def _nest(path: list[str], value: Any) -> dict[str, Any]:
    for part in reversed(path[1:]):
        value = {part: value}
    return {path[0]: value}


def _parse_value(raw: str, path: list[str], label: str) -> Any:
    """Parse a command-line/environment value as a YAML scalar or flow list."""
    annotation = _leaf_annotation(path)
    if annotation == list[str]:
        # Split by hand: YAML cannot read `[udp/[::1]:7447]`, and endpoints hold no commas.
        inner = raw.strip()
        if inner.startswith("[") and inner.endswith("]"):
            inner = inner[1:-1]
        return [item.strip().strip("'\"") for item in inner.split(",") if item.strip()]
    try:
        value = yaml.safe_load(raw) if raw else None
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{label}: cannot parse value {raw!r} as YAML: {problem}") from exc
    # A text field keeps the text: `--set run.name=2024` or `transport.session=on` stay strings.
    if value is not None and not isinstance(value, str) and _accepts_text(annotation):
        return raw
    return value


def _leaf_annotation(path: list[str]) -> Any:
    """The type of the field at `path`, or None when the path names no field."""
    model: type[BaseModel] | None = CpslamConfig
    info = None
    for part in path:
        if model is None:
            return None
        info = model.model_fields.get(part)
        if info is None:
            return None
        model = _model_type(info.annotation)
    return info.annotation if info is not None else None


def _accepts_text(annotation: Any) -> bool:
    if annotation in (str, Path):
        return True
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(a in (str, Path) for a in typing.get_args(annotation))
    return False


def _model_type(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    return None


def _check_keys(model: type[BaseModel], data: Mapping[Any, Any], label: str, prefix: str) -> None:
    """Raise on a key that names no field, listing the valid ones."""
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if not isinstance(key, str) or key not in model.model_fields:
            where = f"section '{prefix[:-1]}'" if prefix else "the top level"
            valid = ", ".join(model.model_fields)
            raise ConfigError(f"{label}: unknown key '{dotted}'; valid keys of {where}: {valid}")
        sub = _model_type(model.model_fields[key].annotation)
        if sub is not None and isinstance(value, Mapping):
            _check_keys(sub, value, label, f"{dotted}.")
        elif sub is None and isinstance(value, Mapping) and value:
            raise ConfigError(
                f"{label}: '{dotted}' is a value, not a section; "
                f"nothing can be set under it ('{dotted}.{next(iter(value))}')"
            )


def _merge(base: dict[str, Any], update: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _leaves(data: Mapping[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key, value in data.items():
        if isinstance(value, Mapping) and value:
            out.extend(_leaves(value, f"{prefix}{key}."))
        else:
            out.append(f"{prefix}{key}")
    return out


def _build(layers: list[_Layer]) -> CpslamConfig:
    merged: dict[str, Any] = {}
    origin: dict[str, str] = {}
    for layer in layers:
        # `section:` with nothing under it reads as null in YAML; treat it as empty.
        data = {k: v for k, v in layer.data.items() if v is not None}
        _check_keys(CpslamConfig, data, layer.label, "")
        merged = _merge(merged, data)
        for key in _leaves(data):
            origin[key] = layer.label
    try:
        return CpslamConfig.model_validate(merged)
    except ValidationError as exc:
        lines = [_describe(err, origin) for err in exc.errors()]
        raise ConfigError("invalid configuration:\n" + "\n".join(lines)) from None


def _describe(err: Mapping[str, Any], origin: Mapping[str, str]) -> str:
    """One line per pydantic error: dotted key, offending value, source and message."""
    dotted = ".".join(str(p) for p in err["loc"])
    message = str(err["msg"]).removeprefix("Value error, ")
    sources = _sources_of(dotted, origin)
    value = err.get("input")
    shown = "" if isinstance(value, Mapping) else f" = {_short_repr(value)}"
    key = dotted or "(top level)"
    return f"  - {key}{shown} (from {sources}): {message}"


def _sources_of(dotted: str, origin: Mapping[str, str]) -> str:
    parts = dotted.split(".") if dotted else []
    # A list item's location ends in its index; its source is the one that set the list.
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        if prefix in origin:
            return origin[prefix]
    # Section-level (cross-field) errors: every source that set something inside.
    inside = sorted({label for key, label in origin.items() if key.startswith(f"{dotted}.")})
    return ", ".join(inside) if inside else "defaults"


def _short_repr(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
