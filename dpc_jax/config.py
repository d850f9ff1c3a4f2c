"""Configuration as data: dataclasses built from dicts and config files, with strict checking.

A run is described by one frozen dataclass (``dpc_jax.training.train_config.TrainConfig``). It comes from a
Python file ``experiments/protocols/configs/NAME.py`` that defines ``CONFIG`` — either the dataclass itself
or a plain ``dict`` of its fields — and is stored beside the checkpoints as JSON, so that a
resumed run can prove it continues the same experiment.

Everything here is generic over dataclasses; the meaning of the fields (and the checks that
relate several of them) lives with the dataclass. Errors are ``ConfigError`` (a ``ValueError``)
whose message names the source and the field, and suggests the closest known key for a typo.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
import runpy
import traceback
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from dpc_jax._io import atomic_write

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration that cannot describe a run: unknown key, wrong type or inconsistent values."""


def _check_value(value: Any, hint: Any, where: str) -> Any:
    """Return ``value`` converted to the type ``hint`` (lists → tuples), or raise ``ConfigError``."""
    origin = typing.get_origin(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        for option in typing.get_args(hint):
            try:
                return _check_value(value, option, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: {value!r} is not of type {_type_name(hint)}")
    if hint is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected None, got {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a sequence ({_type_name(hint)}), got {value!r}")
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_check_value(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values ({_type_name(hint)}), got {value!r}")
        return tuple(
            _check_value(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin in (dict, Mapping) or hint in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if hint is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    raise TypeError(f"{where}: unsupported field type {hint!r}")


def _type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def unknown_key_error(key: str, known: list[str], where: str) -> ConfigError:
    """The error for a key that is not a field, with the closest known key as a hint."""
    close = difflib.get_close_matches(key, known, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else f"; known keys: {', '.join(sorted(known))}"
    return ConfigError(f"{where}: unknown key {key!r}{hint}")


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build the dataclass ``cls`` from ``data``, rejecting unknown keys and mistyped values.

    Values are checked against the field annotations (``int``, ``float``, ``bool``, ``str``,
    ``tuple[...]``, unions with None, ``dict``); JSON lists become tuples. Missing keys take the
    field defaults. The dataclass's own ``__post_init__`` then checks how the fields relate.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping of fields, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    values = {}
    for key, value in data.items():
        if key not in names:
            raise unknown_key_error(str(key), names, where)
        values[key] = _check_value(value, hints[key], f"{where}.{key}")
    try:
        return cls(**values)
    # The dataclass's own checks (a ConfigError) and those of a nested dataclass built from the fields
    # (a ValueError) do not know the source: name it.
    except ValueError as error:
        raise ConfigError(f"{where}: {error}") from None


def to_dict(config: Any) -> dict[str, Any]:
    """The fields of a config dataclass as JSON-compatible data (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def diff(a: Any, b: Any) -> list[str]:
    """Human-readable differences ``key: a → b`` between two configs of the same class."""
    da, db = to_dict(a), to_dict(b)
    return [
        f"{k}: {da.get(k)!r} → {db.get(k)!r}" for k in sorted(set(da) | set(db)) if da.get(k) != db.get(k)
    ]


def load_file(path: str | os.PathLike, cls: type[T], name: str = "CONFIG") -> T:
    """Load ``CONFIG`` (or the variable ``name``) from the Python file ``path``: an instance of ``cls``
    or a dict of its fields.

    A ``.json`` file (as written by ``save_json``) is accepted too. A file that is not valid Python,
    or whose code raises (a misspelt name, a failed import, a dataclass's own check), is a
    ``ConfigError`` naming the file and the line.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    if path.suffix == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise ConfigError(f"{path}: not valid JSON ({error})") from None
        return from_dict(cls, data, where=str(path))
    try:
        namespace = runpy.run_path(str(path))
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    except SyntaxError as error:
        raise ConfigError(f"{path}, line {error.lineno}: not valid Python ({error.msg})") from None
    except Exception as error:  # the file's own code failed (a NameError, a failed import, a check)
        line = next((frame.lineno for frame in reversed(traceback.extract_tb(error.__traceback__))
                     if Path(frame.filename) == path), None)
        where = f"{path}, line {line}" if line is not None else str(path)
        message = str(error).splitlines()[0] if str(error) else ""
        raise ConfigError(f"{where}: running it raised {type(error).__name__}"
                          + (f": {message}" if message else "")) from None
    if name not in namespace:
        raise ConfigError(f"{path}: defines no {name} (expected {name} = {cls.__name__}(...) or a dict)")
    config = namespace[name]
    if isinstance(config, cls):
        return config
    if isinstance(config, Mapping):
        return from_dict(cls, config, where=f"{path}: {name}" if name != "CONFIG" else str(path))
    raise ConfigError(f"{path}: {name} must be a {cls.__name__} or a dict, got {type(config).__name__}")


def save_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` (a dataclass or JSON-compatible value) to ``path`` atomically."""
    path = Path(path)
    if dataclasses.is_dataclass(data) and not isinstance(data, type):
        data = to_dict(data)
    text = json.dumps(data, indent=2, sort_keys=True) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, text)
