"""Typed configuration: pydantic sections with documented defaults and units.

A run's parameters come from defaults, then an optional YAML/TOML file (`--config`), then
command-line flags; the effective config is saved beside the run's outputs.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from mcl3d.core.errors import ConfigError
from mcl3d.core.outputs import write_text_atomic

if sys.version_info >= (3, 11):
    import tomllib
else:  # the same parser, published for Python 3.10
    import tomli as tomllib


class Section(BaseModel):
    """Base of every config section: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


S = TypeVar("S", bound=Section)


def _describe(exc: ValidationError, source: str) -> str:
    first = exc.errors()[0]
    where = ".".join(str(part) for part in first["loc"]) or "config"
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{source}: {where}: {first['msg']}{more}"


def build(cls: type[S], values: dict[str, Any], source: str = "config") -> S:
    """Validate `values` into `cls`, raising ConfigError that names the offending key."""
    try:
        return cls.model_validate(values)
    except ValidationError as exc:
        raise ConfigError(_describe(exc, source)) from None


def load(cls: type[S], path: Path | None, overrides: dict[str, Any] | None = None,
         preset: dict[str, Any] | None = None) -> S:
    """Defaults, then a `preset` (a named set of dotted keys), then the YAML/TOML file at
    `path`, then `overrides` (dotted keys allowed; None values are skipped)."""
    values: dict[str, Any] = {}
    _set_dotted(values, preset or {})
    if path is not None:
        _merge(values, _read_file(Path(path)))
    _set_dotted(values, overrides or {})
    return build(cls, values, str(path) if path else "options")


def _set_dotted(values: dict[str, Any], dotted: dict[str, Any]) -> None:
    for key, value in dotted.items():
        if value is None:
            continue
        node = values
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value


def _merge(values: dict[str, Any], update: dict[str, Any]) -> None:
    """Nested update: a file's section keeps the preset's keys it does not name."""
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(values.get(key), dict):
            _merge(values[key], value)
        else:
            values[key] = value


def _read_file(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    text = path.read_text()
    try:
        data = tomllib.loads(text) if path.suffix == ".toml" else yaml.safe_load(text)
    except (tomllib.TOMLDecodeError, yaml.YAMLError) as exc:
        kind = "TOML" if path.suffix == ".toml" else "YAML"
        raise ConfigError(f"config file {path} is not valid {kind}: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of sections")
    return data


def save(config: BaseModel, path: Path) -> None:
    """Write the effective config as YAML (loadable again with --config)."""
    write_text_atomic(path, yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
