"""One configuration for every gmmap process, assembled from each layer's own section.

Each section is a frozen dataclass owned by its layer, which documents the units and validates
the values (`fit`: gmm_core.FitConfig, `reconstruction`: gmm_core.reconstruct.ReconstructionConfig,
`keyframe`: services.datasets.keyframes.KeyframeConfig, `server`, `agent`, `sim`, `ros2`:
services/*/config.py). Defaults live there once; a config file
(TOML or YAML, `--config FILE`), command-line flags and the Python API all resolve to a
`GmmapConfig`, in that order of precedence: defaults < file < flags. A bad value is a
`ConfigError` that names its field, e.g. `fit.max_range: must be a finite number > 0`.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gmm_core import FitConfig
from gmm_core.reconstruct import ReconstructionConfig
from services.agent.config import AgentConfig
from services.datasets.keyframes import KeyframeConfig
from services.map_server.config import ServerConfig
from services.ros2.config import Ros2Config
from services.sim.config import SimConfig


class ConfigError(ValueError):
    """A configuration that cannot run; the message names the field (`section.field`)."""


@dataclass(frozen=True)
class GmmapConfig:
    fit: FitConfig = field(default_factory=FitConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    server: ServerConfig = field(default_factory=ServerConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)

    def override(self, sections: Mapping[str, Mapping[str, Any]]) -> GmmapConfig:
        """This configuration with the values of `sections` ({section: {field: value}}) in place."""
        known = {f.name for f in dataclasses.fields(self)}
        changed = {}
        for name, values in sections.items():
            if name not in known:
                raise ConfigError(f"{name}: no such section (sections: {', '.join(sorted(known))})")
            if not isinstance(values, Mapping):
                raise ConfigError(f"{name}: must be a table of fields, got {values!r}")
            changed[name] = _override_section(getattr(self, name), name, values)
        return dataclasses.replace(self, **changed)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain JSON types, every field included (None where unset)."""
        return {
            name: {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(section).items()}
            for name, section in self.sections().items()
        }

    def sections(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def to_toml(self) -> str:
        """The configuration as a TOML file that `load_config` reads back to an equal one."""
        lines = []
        for name, values in self.to_dict().items():
            lines.append(f"[{name}]")
            lines += [f"{key} = {json.dumps(value)}" for key, value in values.items() if value is not None]
            lines.append("")
        return "\n".join(lines)


def summary(**sections: Any) -> str:
    """One line of JSON with the given sections, for a process to log the configuration it runs."""
    return json.dumps({name: dataclasses.asdict(section) for name, section in sections.items()}, sort_keys=True)


def load_config(
    path: str | Path | None = None, overrides: Mapping[str, Mapping[str, Any]] | None = None
) -> GmmapConfig:
    """Defaults, then the file at `path` (TOML `.toml`, YAML `.yaml`/`.yml`), then `overrides`."""
    config = GmmapConfig()
    if path is not None:
        config = config.override(read_config_file(Path(path)))
    return config.override(overrides or {})


def read_config_file(path: Path) -> dict[str, Any]:
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".yaml", ".yml"):
        raise ConfigError(f"--config: {path} must end in .toml, .yaml or .yml")
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"--config: cannot read {path}: {error.strerror}") from None
    try:
        data = _toml().loads(text) if suffix == ".toml" else (_yaml().safe_load(text) or {})
    except ConfigError:
        raise
    except Exception as error:  # the parsers' own error types: TOMLDecodeError, YAMLError
        raise ConfigError(f"--config: {path} is not valid {suffix[1:].upper()}: {error}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"--config: {path} must hold sections (tables), got {type(data).__name__}")
    return data


def _toml():
    if sys.version_info >= (3, 11):
        import tomllib

        return tomllib
    import tomli  # the same parser, for Python 3.10 (a dependency there)

    return tomli


def _yaml():
    try:
        import yaml
    except ImportError:
        raise ConfigError("--config: a YAML file needs PyYAML (pip install pyyaml), or use TOML") from None
    return yaml


def _override_section(section: Any, name: str, values: Mapping[str, Any]) -> Any:
    hints = typing.get_type_hints(type(section))
    fields = {f.name for f in dataclasses.fields(section)}
    coerced = {}
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{name}.{key}: no such field (fields of [{name}]: {', '.join(sorted(fields))})")
        coerced[key] = _coerce(f"{name}.{key}", hints[key], value)
    try:
        return dataclasses.replace(section, **coerced)
    except ConfigError:
        raise
    except ValueError as error:  # the section's own validation, which names the field
        raise ConfigError(str(error)) from None


def _coerce(where: str, hint: Any, value: Any) -> Any:
    """`value` as the field's declared type: int, float, str, bool, tuple[str, ...], or X | None."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        if value is None:
            return None
        (hint,) = [a for a in args if a is not type(None)]
        args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, (list, tuple)) or not all(isinstance(v, str) for v in items):
            raise ConfigError(f"{where}: must be a list of strings, got {value!r}")
        return tuple(items)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and (type(value) is not hint):
        raise ConfigError(f"{where}: must be {hint.__name__}, got {value!r}")
    return value
