"""YAML config files, ``--set`` overrides and schema checking.

A config file is YAML whose top-level keys are the sections of :class:`Config`. It is checked
against the schema by pydantic (strict types: ``true`` is not an integer, ``"3"`` is not a
number): an unknown key or a value of the wrong type raises
:class:`~torchfit.errors.ConfigError` naming the dotted key, the file and the valid keys or
choices. Overrides use dotted keys, ``--set solver.max_iter=50``; the value is parsed as YAML
(``50`` is an int, ``[1, 2]`` a list, ``null`` None).

Input paths (:data:`PATH_KEYS`: ``data.root``, and ``model.template`` where it names a
``.urdf`` file) are made absolute when loading: a relative path written in a config file is
taken from the file's folder (so a config runs from any working directory), one given with
``--set`` from the current directory. Output paths (``run.out``, the default ``runs/<name>``)
stay relative to the current directory.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union

import yaml
from pydantic import ConfigDict, TypeAdapter, ValidationError

from torchfit.config.schema import Config
from torchfit.errors import ConfigError, yaml_problem

__all__ = [
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "apply_overrides",
    "save_config",
    "config_to_yaml",
    "parse_yaml",
    "PATH_KEYS",
    "replace_keys",
]


# --------------------------------------------------------------------------------------------
# YAML: PyYAML follows YAML 1.1, where ``1e-3`` is a string; accept YAML 1.2 floats.


class _Loader(yaml.SafeLoader):
    pass


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` that also reads ``1e-3`` as a float (YAML 1.2 numbers)."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass


# --------------------------------------------------------------------------------------------
# Error messages from pydantic's


_EXPECTS = {
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "float_type": "a number",
    "float_parsing": "a number",
    "bool_type": "a boolean (true/false)",
    "bool_parsing": "a boolean (true/false)",
    "string_type": "a string",
    "list_type": "a list",
    "tuple_type": "a list",
    "dict_type": "a mapping",
    "dataclass_type": "a mapping",
    "dataclass_exact_type": "a mapping",
    "model_type": "a mapping",
}


def _strip(tp: Any) -> Any:
    """The non-None member of ``X | None``."""
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return _strip(args[0])
    return tp


def _walk(schema: type, loc: tuple) -> tuple[str, Any]:
    """The dotted key of a pydantic error location and the schema type it ends at (union
    member tags in ``loc`` are skipped)."""
    key, tp = "", schema
    for part in loc:
        tp = _strip(tp)
        origin = typing.get_origin(tp)
        if isinstance(part, int) and origin in (list, tuple):
            key += f"[{part}]"
            tp = typing.get_args(tp)[0]
        elif dataclasses.is_dataclass(tp) and isinstance(part, str):
            hints = typing.get_type_hints(tp)
            key = f"{key}.{part}" if key else part
            tp = hints.get(part, Any)
        elif origin is dict:
            key = f"{key}.{part}" if key else str(part)
            tp = typing.get_args(tp)[1]
    return key, tp


def _message(error: dict, schema: type, source: str) -> str:
    kind, loc, value = error["type"], tuple(error["loc"]), error.get("input")
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        parent, tp = _walk(schema, loc[:-1])
        where = f"{parent}." if parent else ""
        names = sorted(f.name for f in dataclasses.fields(_strip(tp)))
        under = f" under '{parent}'" if parent else ""
        return f"{source}: unknown key '{where}{loc[-1]}' (valid keys{under}: {', '.join(names)})"
    missing_item = kind == "missing" and loc and isinstance(loc[-1], int)
    if kind in ("too_long", "too_short") or missing_item:
        key, tp = _walk(schema, loc[:-1] if kind == "missing" else loc)
        args = typing.get_args(_strip(tp))
        n = len(args) if args and args[-1] is not Ellipsis else None
        expects = f"a list of {n} values" if n else "a list of a different length"
        return f"{source}: key '{key}' expects {expects}, got {value!r}"
    key, tp = _walk(schema, loc)
    if kind == "literal_error":
        tp = _strip(tp)
        choices = list(typing.get_args(tp)) if typing.get_origin(tp) is Literal else []
        return f"{source}: key '{key}' must be one of {choices}, got {value!r}"
    if kind in _EXPECTS:
        return (
            f"{source}: key '{key}' expects {_EXPECTS[kind]}, got {type(value).__name__} {value!r}"
        )
    if kind == "value_error":
        text = str(error.get("ctx", {}).get("error", error["msg"]))
        return f"{source}: key '{key}': {text}" if key else f"{source}: {text}"
    return f"{source}: key '{key}': {error['msg']} (got {value!r})"


def _plain_json(data: Any, source: str) -> str:
    """``data`` as JSON, for pydantic's strict JSON mode (where a YAML list may fill a tuple
    field and an int a float field, but nothing else is coerced)."""

    def check(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return v
        if isinstance(v, dict):
            return {str(k): check(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [check(x) for x in v]
        if v is None or isinstance(v, (str, int, float, bool)):
            return v
        raise ConfigError(f"{source}: value {v!r} is not a plain YAML scalar, list or mapping")

    return json.dumps(check(data))


_ADAPTERS: dict[type, TypeAdapter] = {}


def config_from_dict(data: dict | None, source: str = "<dict>", schema: type = Config) -> Any:
    """Build a config dataclass from a plain dict, checking every key and type.

    Args:
        data: nested mapping (as loaded from YAML); ``None`` gives the defaults.
        source: name used in error messages (usually the file path).
        schema: the dataclass to build (default :class:`Config`).

    Raises:
        ConfigError: naming the dotted key and ``source``.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping, got {type(data).__name__}")
    adapter = _ADAPTERS.get(schema)
    if adapter is None:
        # a one-element tuple around the schema, so that the strictness settings reach the
        # plain dataclasses inside (pydantic takes no config for a dataclass itself)
        adapter = TypeAdapter(tuple[schema], config=ConfigDict(extra="forbid", strict=True))
        _ADAPTERS[schema] = adapter
    try:
        return adapter.validate_json(_plain_json([data], source))[0]
    except ValidationError as exc:
        error = exc.errors()[0]
        error["loc"] = tuple(error["loc"])[1:]
        raise ConfigError(_message(error, schema, source)) from None


def config_to_dict(config: Any) -> dict:
    """The plain-dict form of a config dataclass (tuples become lists), ready for YAML."""

    def plain(v: Any) -> Any:
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(dataclasses.asdict(config))


def apply_overrides(data: dict, overrides: list[str], source: str = "--set") -> dict:
    """Apply ``a.b.c=value`` overrides to a nested dict (values parsed as YAML).

    Raises:
        ConfigError: for an override without ``=`` or a value that is not valid YAML.
    """
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"{source}: override {item!r} must look like key.sub=value")
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"{source}: override {item!r} has an empty key")
        try:
            value = parse_yaml(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"{source}: value of '{key}' is not valid YAML: {exc}") from exc
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(f"{source}: cannot set '{key}': '{part}' is not a mapping")
            node = child
        node[parts[-1]] = value
    return data


#: Keys that name input files or folders (made absolute by :func:`load_config`).
PATH_KEYS = ("data.root", "model.template")


def _absolute_paths(data: dict, base: Path) -> None:
    """Make the relative :data:`PATH_KEYS` values in ``data`` absolute, from ``base``."""
    for key in PATH_KEYS:
        section, name = key.split(".")
        node = data.get(section)
        value = node.get(name) if isinstance(node, dict) else None
        if not isinstance(value, str) or not value or os.path.isabs(value):
            continue
        if key == "model.template" and not value.lower().endswith(".urdf"):
            continue  # a shipped template's name
        node[name] = os.path.normpath(os.path.join(os.path.abspath(base), value))


def load_config(
    path: str | Path | None,
    overrides: list[str] | None = None,
    schema: type = Config,
) -> Any:
    """Load a YAML config file, apply ``--set`` overrides and check it against ``schema``.

    Args:
        path: the YAML file; ``None`` starts from the defaults.
        overrides: ``["solver.max_iter=50", ...]``.
        schema: the dataclass to build (default :class:`Config`).

    Relative input paths (:data:`PATH_KEYS`) become absolute: from the file's folder when
    the file sets them, from the current directory when an override does.

    Raises:
        ConfigError: for a missing file, invalid YAML, an unknown key or a wrong type; the
            message names the key and the file.
    """
    source = str(path) if path is not None else "<defaults>"
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = parse_yaml(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML: {yaml_problem(exc)}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the top level must be a mapping, got {type(data).__name__}")
        _absolute_paths(data, path.parent)
    if overrides:
        apply_overrides(data, overrides)
        _absolute_paths(data, Path.cwd())
        source = f"{source} (with --set overrides)"
    return config_from_dict(data, source, schema)


def replace_keys(config: Any, values: dict[str, Any]) -> Any:
    """A copy of a (frozen) config with dotted keys replaced, e.g.
    ``replace_keys(config, {"run.resume": False, "fit.batch_size": 8})``. The values are
    taken as given (not checked against the schema).

    Raises:
        ConfigError: a key that is not in the config.
    """
    for key, value in values.items():
        config = _replace(config, key.split("."), value, key)
    return config


def _replace(node: Any, parts: list[str], value: Any, key: str) -> Any:
    if not dataclasses.is_dataclass(node) or parts[0] not in {
        f.name for f in dataclasses.fields(node)
    }:
        raise ConfigError(f"replace_keys: unknown key {key!r}")
    child = value if len(parts) == 1 else _replace(getattr(node, parts[0]), parts[1:], value, key)
    return dataclasses.replace(node, **{parts[0]: child})


def config_to_yaml(config: Any) -> str:
    """The YAML text of a config (what :func:`save_config` writes)."""
    return yaml.safe_dump(config_to_dict(config), sort_keys=False)


def save_config(config: Any, path: str | Path) -> None:
    """Write the resolved config as YAML (the runs write it atomically with
    :func:`torchfit.io.files.write_atomic` and :func:`config_to_yaml`)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(config_to_yaml(config))
