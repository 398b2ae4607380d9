"""Load YAML into a pydantic model; errors name file, line and key: `x.yaml:14: soak.tolerance_c must be > 0`.

YAML is composed safely (no arbitrary objects), keeping each node's position, so a
validation error on ('soak', 'tolerance_c') points at the line of that key.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from labrunner.errors import UserError

M = TypeVar("M", bound=BaseModel)


class ConfigError(UserError):
    """A configuration file (procedure, lab, sim) that cannot be used; says where and why."""

    def __init__(self, messages: list[str]) -> None:
        self.messages = messages
        super().__init__("\n".join(messages))


def _positions(node: yaml.Node, path: tuple[Any, ...], out: dict[tuple[Any, ...], int]) -> None:
    out.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            key = key_node.value
            out[path + (key,)] = key_node.start_mark.line + 1
            _positions(value_node, path + (key,), out)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _positions(item, path + (i,), out)


def load_yaml(text: str, source: str) -> tuple[Any, dict[tuple[Any, ...], int]]:
    """Parse YAML safely; returns the data and a map from key path to line number."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.load(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f":{mark.line + 1}" if mark else ""
        problem = exc.problem or str(exc)
        raise ConfigError([f"{source}{line}: not valid YAML: {problem}"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([f"{source}: not valid YAML: {exc}"]) from None
    except (RecursionError, ValueError, TypeError) as exc:  # pathological input (deep nesting, huge numbers)
        raise ConfigError([f"{source}: cannot read YAML: {type(exc).__name__}"]) from None
    positions: dict[tuple[Any, ...], int] = {}
    if node is not None:
        _positions(node, (), positions)
    return data, positions


def _describe(err: Mapping[str, Any]) -> str:
    kind = err.get("type", "")
    ctx = err.get("ctx") or {}
    if kind == "missing":
        return "is required"
    if kind == "extra_forbidden":
        return "is not a known key"
    if kind == "greater_than":
        return f"must be > {ctx.get('gt')}"
    if kind == "greater_than_equal":
        return f"must be >= {ctx.get('ge')}"
    if kind == "less_than":
        return f"must be < {ctx.get('lt')}"
    if kind == "less_than_equal":
        return f"must be <= {ctx.get('le')}"
    if kind in ("float_parsing", "float_type", "int_parsing", "int_type", "int_from_float"):
        return f"must be a number, got {err.get('input')!r}"
    if kind in ("finite_number",):
        return "must be a finite number"
    if kind in ("bool_parsing", "bool_type"):
        return f"must be true or false, got {err.get('input')!r}"
    if kind in ("string_type",):
        return f"must be text, got {err.get('input')!r}"
    if kind in ("list_type", "tuple_type"):
        return "must be a list"
    if kind in ("dict_type", "model_type", "model_attributes_type"):
        return "must be a mapping of keys to values"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected')}, got {err.get('input')!r}"
    if kind == "enum":
        return f"must be one of {ctx.get('expected')}, got {err.get('input')!r}"
    if kind == "too_short":
        return f"must have at least {ctx.get('min_length')} item(s)"
    if kind == "too_long":
        return f"must have at most {ctx.get('max_length')} item(s)"
    if kind == "value_error":
        msg = str(ctx.get("error", err.get("msg", "")))
        return msg
    return str(err.get("msg", "is not valid"))


def _located(source: str, positions: Mapping[tuple[Any, ...], int], loc: tuple[Any, ...]) -> str:
    # The deepest path that exists in the file (a missing key points at its parent mapping).
    path = tuple(p for p in loc if not (isinstance(p, str) and p.startswith(("function-", "union["))))
    for n in range(len(path), -1, -1):
        if path[:n] in positions:
            return f"{source}:{positions[path[:n]]}"
    return source


def _dotted(loc: tuple[Any, ...]) -> str:
    parts: list[str] = []
    for p in loc:
        if isinstance(p, int):
            parts.append(f"[{p}]")
        elif isinstance(p, str) and p.startswith(("function-", "union[")):
            continue
        else:
            parts.append(("." if parts else "") + str(p))
    return "".join(parts) or "(top level)"


def validate(model: type[M], data: Any, positions: Mapping[tuple[Any, ...], int], source: str) -> M:
    """Validate parsed YAML into `model`, raising ConfigError with one located line per problem."""
    if not isinstance(data, Mapping):
        kind = "empty" if data is None else f"a {type(data).__name__}"
        raise ConfigError([f"{source}:1: expected a mapping of keys to values, the file is {kind}"])
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors(include_url=False):
            loc = tuple(err.get("loc", ()))
            lines.append(f"{_located(source, positions, loc)}: {_dotted(loc)} {_describe(err)}")
        raise ConfigError(lines) from None


def read_text(path: str | Path) -> str:
    """A configuration file's text; a missing or unreadable file is a ConfigError naming it."""
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError([f"{p}: file not found"]) from None
    except IsADirectoryError:
        raise ConfigError([f"{p}: is a directory; expected a YAML file"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError([f"{p}: cannot read: {exc}"]) from None


def load_model(model: type[M], path: str | Path) -> tuple[M, str]:
    """Read a YAML file into `model`; returns the model and the file's text."""
    text = read_text(path)
    data, positions = load_yaml(text, str(path))
    return validate(model, data, positions, str(path)), text
