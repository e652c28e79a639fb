"""One TOML config for every service, a section each; defaults are the paper's Table I values.

Each package owns a frozen config dataclass with its defaults (``services/tracker/config.py:
TrackerConfig`` and so on); this module loads a TOML file, applies command-line overrides
(``--set tracker.mahalanobis_rb=0.3``), and builds those dataclasses, rejecting unknown keys and
wrong types with an error that names the section and key.

Sections: ``zenoh`` (:class:`~services.common.bus.ZenohOptions`), ``limits`` and ``stamps`` (the
input guards every service shares), ``tracker``, ``kinematics``, and whatever other packages
register in :data:`SECTIONS`.
"""

from __future__ import annotations

import dataclasses
import importlib
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

T = TypeVar("T")

# section name -> "module:Class" of its config dataclass (imported lazily).
SECTIONS: dict[str, str] = {
    "zenoh": "services.common.bus:ZenohOptions",
    "limits": "services.common.service:ServiceLimits",
    "stamps": "services.common.stamps:StampLimits",
    "tracker": "services.tracker.config:TrackerConfig",
    "kinematics": "services.kinematics.config:KinematicsConfig",
    "segmentation": "services.kinematics.contact:SegmentationConfig",
    "detector": "services.detector.config:DetectorConfig",
    "robot_bridge": "services.robot_bridge.config:RobotBridgeConfig",
}


class ConfigError(ValueError):
    """A config file or override that does not fit; the message names section and key."""


def section_class(name: str) -> type[Any]:
    """The dataclass registered for a section."""
    if name not in SECTIONS:
        raise ConfigError(f"unknown config section [{name}]; known: {sorted(SECTIONS)}")
    module, _, cls = SECTIONS[name].partition(":")
    return getattr(importlib.import_module(module), cls)  # type: ignore[no-any-return]


def load_toml(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError as exc:
        raise ConfigError(f"config file {path} does not exist") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from exc


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"section.key=value"`` -> (section, key, value); the value is a TOML literal or a string."""
    lhs, sep, rhs = text.partition("=")
    section, dot, key = lhs.strip().partition(".")
    if not sep or not dot or not section or not key:
        raise ConfigError(f"override {text!r} must look like section.key=value")
    try:
        value = tomllib.loads(f"v = {rhs.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = rhs.strip()
    return section, key, value


def merged(path: str | Path | None = None, overrides: Sequence[str] = ()) -> dict[str, dict[str, Any]]:
    """Raw section dicts: the file (if any) with the overrides applied on top."""
    raw = load_toml(path) if path else {}
    out: dict[str, dict[str, Any]] = {}
    for name, values in raw.items():
        if not isinstance(values, dict):
            raise ConfigError(f"config key {name!r} must be a [section]")
        section_class(name)
        out[name] = dict(values)
    for text in overrides:
        section, key, value = parse_override(text)
        section_class(section)
        out.setdefault(section, {})[key] = value
    return out


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        item = args[0] if args else Any
        return tuple(_coerce(v, item, where) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def build(cls: type[T], values: Mapping[str, Any], section: str) -> T:
    """Instantiate config dataclass ``cls`` from ``values`` (defaults for what is missing)."""
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ConfigError(f"[{section}] has unknown keys {unknown}; known: {sorted(fields)}")
    kwargs = {k: _coerce(v, hints[k], f"[{section}] {k}") for k, v in values.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[{section}] {exc}") from exc


def load_section(name: str, path: str | Path | None = None, overrides: Sequence[str] = ()) -> Any:
    """The config dataclass of one section, from file + overrides + defaults."""
    return build(section_class(name), merged(path, overrides).get(name, {}), name)


def section_from_args(args: Any, name: str) -> Any:
    """Section ``name`` from the CLI's ``--config FILE`` and ``--set`` overrides."""
    return load_section(name, getattr(args, "config", None), getattr(args, "overrides", ()))


def to_toml(sections: Mapping[str, Any]) -> str:
    """Render config dataclasses as TOML (flat scalar, string and list fields)."""

    def literal(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(literal(x) for x in v) + "]"
        return repr(v)

    lines: list[str] = []
    for name, obj in sections.items():
        lines.append(f"[{name}]")
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if v is None:
                lines.append(f"# {f.name} = (unset)")
            else:
                lines.append(f"{f.name} = {literal(v)}")
        lines.append("")
    return "\n".join(lines)
