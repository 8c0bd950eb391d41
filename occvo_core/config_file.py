"""Config files (JSON5) read into a pydantic model; what is wrong in one is one line naming each wrong key or value
and what is allowed there."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import TypeVar, get_args

from pydantic import BaseModel, ValidationError

from occvo_core.errors import ConfigError

M = TypeVar("M", bound=BaseModel)


def read(path: str | Path) -> dict:
    """The file's JSON5 object; a file that cannot be read or is not one is a ConfigError."""
    import json5

    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        data = json5.loads(text)
    except ValueError as exc:
        raise ConfigError(f"{path}: not JSON5 ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: must hold one object of keys, not a {type(data).__name__}")
    return data


def validate(model: type[M], data: dict, where: str | Path) -> M:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{where}: {validation_line(model, exc)}") from None


def _section(annotation) -> type[BaseModel] | None:
    """The model a field holds: itself, or the items of a list or the value of an optional."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        if (found := _section(arg)) is not None:
            return found
    return None


def _model_at(model: type[BaseModel], loc: tuple) -> type[BaseModel] | None:
    """The section (model) that holds the keys at loc, or None where loc leaves the sections."""
    for key in loc:
        if isinstance(key, int):  # an item of a list of sections
            continue
        field = model.model_fields.get(key)
        model = _section(field.annotation) if field is not None else None
        if model is None:
            return None
    return model


def _home(model: type[BaseModel], key: str, path: tuple = ()) -> str | None:
    """The section where key belongs (a key given in the wrong section)."""
    for name, field in model.model_fields.items():
        sub = _section(field.annotation)
        if sub is None:
            continue
        if key in sub.model_fields:
            return ".".join((*path, name))
        if (deeper := _home(sub, key, (*path, name))) is not None:
            return deeper
    return None


def _keys(model: type[BaseModel]) -> str:
    return ", ".join(model.model_fields)


def _unknown(model: type[BaseModel], section_loc: tuple, keys: list[str]) -> str:
    section = _model_at(model, section_loc)
    allowed = list(section.model_fields) if section else []
    hints = []
    for key in keys:
        close = difflib.get_close_matches(key, allowed, n=1)
        home = None if close else _home(model, key)
        if close or home:
            hint = f"did you mean {close[0]}?" if close else f"it belongs in {home}"
            hints.append(hint if len(keys) == 1 else f"{key}: {hint}")
    prefix = ".".join(str(k) for k in section_loc)
    names = ", ".join(f"{prefix}.{k}" if prefix else k for k in keys)
    hint = "; ".join(hints) + "; " if hints else ""
    return f"{names}: unknown key{'s' if len(keys) > 1 else ''} ({hint}allowed: {', '.join(allowed)})"


def _problem(model: type[BaseModel], error: dict) -> str:
    loc = tuple(error["loc"])
    where = ".".join(str(k) for k in loc) or "the file"
    kind = error["type"]
    if kind == "missing":
        return f"{where}: missing (required)"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        section = _model_at(model, loc)
        if section is not None:
            return f"{where}: must be a section of keys (allowed: {_keys(section)}), not {error['input']!r}"
    msg = error["msg"]
    msg = msg[:1].lower() + msg[1:]
    if msg.startswith("value error, "):
        return f"{where}: {msg[len('value error, ') :]}"
    return f"{where}: {error['input']!r} is not allowed: {msg}"


def validation_line(model: type[BaseModel], exc: ValidationError) -> str:
    """Every error of exc, '; '-joined, unknown keys of a section together:
    `gicp.souce_pick: unknown key (did you mean source_pick?; allowed: wide_voxel_m, ...)`."""
    unknown: dict[tuple, list[str]] = {}
    problems = []
    for e in exc.errors():
        if e["type"] == "extra_forbidden":
            unknown.setdefault(tuple(e["loc"][:-1]), []).append(str(e["loc"][-1]))
        else:
            problems.append(_problem(model, e))
    problems += [_unknown(model, loc, keys) for loc, keys in unknown.items()]
    return "; ".join(dict.fromkeys(problems))
