"""Load YAML into a pydantic model; errors name file, line and key: `x.yaml:14: soak.tolerance_c must be > 0`.

YAML is composed safely (no arbitrary objects), keeping each node's position, so a
validation error on ('soak', 'tolerance_c') points at the line of that key. This is the
one YAML reader of labrunner (procedures, lab and sim configurations, IMU models): it refuses
what could hang or exhaust a run before anything is built from it: a document over
`MAX_DOCUMENT_BYTES`, duplicate keys (YAML would silently keep the last), more than
`MAX_ALIASES` aliases or a document whose aliases expand past `MAX_NODES` values (an alias
bomb), nesting deeper than `MAX_DEPTH`, and numbers of absurd length.

Numbers a schema uses get a finite, physical range (`Range`), listed in one table per schema
(`procedure.RANGES`, `lab.RANGES`, `sim_config.RANGES`) and checked by `RangedModel` (pydantic
schemas) or `check_ranges` (plain mappings) before any other check computes with them.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from labrunner.errors import UserError

M = TypeVar("M", bound=BaseModel)

MAX_DOCUMENT_BYTES = 1_000_000  # a procedure or configuration is a few kB; 1 MB leaves room for a big IMU model
MAX_ALIASES = 100  # a hand-written file needs a few
MAX_NODES = 100_000  # values once aliases are expanded: stops a "billion laughs" before it is walked
MAX_DEPTH = 40  # mappings and lists within each other
MAX_NUMBER_CHARS = 64  # a number written with more characters than this is not a physical quantity


class ConfigError(UserError):
    """A configuration file (procedure, lab, sim) that cannot be used; says where and why."""

    def __init__(self, messages: list[str]) -> None:
        self.messages = messages
        super().__init__("\n".join(messages))


# --- ranges ---------------------------------------------------------------------------------------


def show_number(value: Any) -> str:
    """A value for a message, as YAML writes it; huge integers by their size (their digits could be thousands)."""
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**15:
        return f"{'-' if value < 0 else ''}an integer of {value.bit_length()} bits"
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value)


@dataclass(frozen=True)
class Range:
    """The values a number may take: finite, within lo..hi (inclusive), whole if `integer`; null only if
    `nullable` (in plain mappings; a pydantic schema says so in its field's type)."""

    lo: float
    hi: float
    unit: str = ""
    integer: bool = False
    nullable: bool = False

    def describe(self) -> str:
        def num(v: float) -> str:
            return f"{int(v)}" if self.integer else f"{v:g}"

        return f"{num(self.lo)}..{num(self.hi)}{' ' + self.unit if self.unit else ''}"

    def problem(self, value: Any) -> str | None:
        """Why `value` is not allowed (as the end of a sentence naming the key), or None."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            kind = "a whole number" if self.integer else "a number"
            return f"must be {kind} in {self.describe()}, got {show_number(value)}"
        if isinstance(value, float):
            if not math.isfinite(value):
                return f"must be a finite number in {self.describe()}, got {value}"
            if self.integer and not value.is_integer():
                return f"must be a whole number in {self.describe()}, got {value:g}"
        if not self.lo <= value <= self.hi:
            return f"must be in {self.describe()}, got {show_number(value)}"
        return None


class RangedModel(BaseModel):
    """A strict schema section (unknown keys refused) whose numbers are checked against a range table.

    `SECTION` is the section's dotted path ("" at the top, "soak", "rates.triangular"); `RANGES`
    maps a field's full dotted path to its `Range`. A ranged field takes a number (a list field: a
    list of numbers) as written, never text or a boolean (`record_s: true` is not 1 s), and the
    range is checked before the section's own validators run."""

    model_config = ConfigDict(extra="forbid")
    SECTION: ClassVar[str] = ""
    RANGES: ClassVar[Mapping[str, Range]] = {}

    @field_validator("*", mode="before")
    @classmethod
    def _in_range(cls, value: Any, info: ValidationInfo) -> Any:
        name = info.field_name or ""
        r = cls.RANGES.get(f"{cls.SECTION}.{name}" if cls.SECTION else name)
        if r is None or value is None:
            return value
        if isinstance(value, list):
            for i, item in enumerate(value):
                problem = r.problem(item)
                if problem:
                    raise ValueError(f"[{i}] {problem}")
            return value
        problem = r.problem(value)
        if problem:
            raise ValueError(problem)
        return value


def _walk(data: Any, parts: list[str], path: tuple[Any, ...]) -> Iterator[tuple[tuple[Any, ...], Any]]:
    """(path, value) of every value at a dotted path with `[]` list wildcards, as far as the data go."""
    if not parts:
        yield path, data
        return
    head, rest = parts[0], parts[1:]
    wildcard = head.endswith("[]")
    key = head[:-2] if wildcard else head
    if not isinstance(data, Mapping) or key not in data:
        return
    value = data[key]
    if wildcard:
        if isinstance(value, list):
            for i, item in enumerate(value):
                yield from _walk(item, rest, path + (key, i))
        return
    yield from _walk(value, rest, path + (key,))


def check_ranges(data: Any, ranges: Mapping[str, Range], positions: Mapping[tuple[Any, ...], int],
                 source: str) -> list[str]:
    """Range problems of a plain mapping (a sim configuration), one located line each."""
    problems = []
    for dotted, r in ranges.items():
        for path, value in _walk(data, dotted.split("."), ()):
            if value is None and r.nullable:
                continue
            problem = r.problem(value)
            if problem:
                problems.append(f"{_located(source, positions, path)}: {_dotted(path)} {problem}")
    return problems


def did_you_mean(word: Any, known: Any) -> str:
    """' (did you mean 'x'?)' when a known name is close to `word`, else ''."""
    close = difflib.get_close_matches(str(word), [str(k) for k in known], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


# --- reading YAML -----------------------------------------------------------------------------------


class _Refused(Exception):
    def __init__(self, line: int | None, message: str) -> None:
        self.line = line
        self.message = message


class _Loader(yaml.SafeLoader):
    """The safe loader, counting aliases as they are composed (the line of the one too many)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                raise _Refused(self.peek_event().start_mark.line + 1,
                               f"more than {MAX_ALIASES} YAML aliases (*name); write the values out")
        return super().compose_node(parent, index)


# YAML 1.1 (PyYAML) reads `1e-9` and `1e3` as text; people mean numbers (YAML 1.2 reads them so).
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")


def _check_tree(root: yaml.Node) -> None:
    """Duplicate keys, depth, number lengths and the expanded size of a composed document."""
    sizes: dict[int, int] = {}  # id(node) -> values under it once aliases are expanded
    open_nodes: set[int] = set()

    def size(node: yaml.Node, depth: int) -> int:
        line = node.start_mark.line + 1
        if id(node) in sizes:
            return sizes[id(node)]
        if id(node) in open_nodes:
            raise _Refused(line, "an alias refers to the mapping or list it is part of (a recursive document)")
        if depth > MAX_DEPTH:
            raise _Refused(line, f"nested more than {MAX_DEPTH} levels deep")
        n = 1
        if isinstance(node, yaml.ScalarNode):
            if node.tag in _NUMBER_TAGS and len(node.value) > MAX_NUMBER_CHARS:
                raise _Refused(line, f"a number written with {len(node.value):,} characters")
        else:
            open_nodes.add(id(node))
            if isinstance(node, yaml.MappingNode):
                seen: dict[Any, int] = {}
                for key_node, value_node in node.value:
                    if isinstance(key_node, yaml.ScalarNode) and key_node.tag != "tag:yaml.org,2002:merge":
                        key_line = key_node.start_mark.line + 1
                        if key_node.value in seen:
                            raise _Refused(key_line, f"duplicate key '{key_node.value}' (first at line "
                                                     f"{seen[key_node.value]}); each key may appear once")
                        seen[key_node.value] = key_line
                    n += size(key_node, depth + 1) + size(value_node, depth + 1)
            else:
                for item in node.value:
                    n += size(item, depth + 1)
            open_nodes.discard(id(node))
        if n > MAX_NODES:
            raise _Refused(line, f"the document expands to more than {MAX_NODES:,} values (aliases expanded)")
        sizes[id(node)] = n
        return n

    size(root, 0)


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
    if len(text.encode("utf-8", errors="replace")) > MAX_DOCUMENT_BYTES:
        raise ConfigError([f"{source}: the document is larger than {MAX_DOCUMENT_BYTES:,} bytes; a procedure or "
                           "configuration is a few kB"])
    loader: _Loader | None = None
    try:
        loader = _Loader(text)
        node = loader.get_single_node()
        if node is not None:
            _check_tree(node)
        data = loader.construct_document(node) if node is not None else None
    except _Refused as exc:
        line = f":{exc.line}" if exc.line else ""
        raise ConfigError([f"{source}{line}: {exc.message}"]) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f":{mark.line + 1}" if mark else ""
        problem = exc.problem or str(exc)
        raise ConfigError([f"{source}{line}: not valid YAML: {problem}"]) from None
    except yaml.reader.ReaderError as exc:  # a character YAML does not allow (binary data, control codes)
        at = text[: exc.position].count("\n") + 1
        raise ConfigError([f"{source}:{at}: not valid YAML: character U+{exc.character:04X} is not allowed "
                           "(is this a text file?)"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([f"{source}: not valid YAML: {exc}"]) from None
    except RecursionError:
        raise ConfigError([f"{source}: not valid YAML: nested too deeply"]) from None
    except (ValueError, TypeError, OverflowError) as exc:  # pathological input the checks above did not foresee
        raise ConfigError([f"{source}: cannot read YAML: {type(exc).__name__}"]) from None
    finally:
        if loader is not None:
            loader.dispose()
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
    if kind == "finite_number":
        return "must be a finite number"
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


def _fields_at(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The field names of the schema section at `loc` (for "did you mean"), [] when unknown."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue  # a list's item: the list's item type was taken below
        if not (isinstance(current, type) and issubclass(current, BaseModel)) or part not in current.model_fields:
            return []
        current = _section_type(current.model_fields[part].annotation)
    if isinstance(current, type) and issubclass(current, BaseModel):
        return list(current.model_fields)
    return []


def _section_type(annotation: Any) -> Any:
    """The BaseModel inside an annotation (`Soak`, `Soak | None`, `list[Orientation]`), or None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if get_origin(annotation) is not None:  # X | None, list[X], Optional[X]
        for arg in get_args(annotation):
            found = _section_type(arg)
            if found is not None:
                return found
    return None


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
            what = _describe(err)
            if err.get("type") == "extra_forbidden" and loc:
                what += did_you_mean(loc[-1], _fields_at(model, tuple(p for p in loc[:-1] if not (
                    isinstance(p, str) and p.startswith(("function-", "union["))))))
            elif err.get("type") == "value_error" and what.startswith(("[", ".")):
                # A problem inside the value (a list's item, a mapping's key): it joins the key path
                # (`rates.list_dps[2] must be ...`, `chamber.profile.setpoint must be ...`).
                inner, _, what = what.partition(" ")
                loc = loc + ((int(inner[1:-1]),) if inner.startswith("[") else (inner[1:],))
            lines.append(f"{_located(source, positions, loc)}: {_dotted(loc)} {what}")
        raise ConfigError(lines) from None


def read_text(path: str | Path) -> str:
    """A configuration file's text; a missing, unreadable, oversized or non-UTF-8 file is a ConfigError
    naming it (a file is read only up to the size limit, so a huge or endless one costs nothing)."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_DOCUMENT_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError([f"{p}: file not found"]) from None
    except IsADirectoryError:
        raise ConfigError([f"{p}: is a directory; expected a YAML file"]) from None
    except OSError as exc:
        raise ConfigError([f"{p}: cannot read: {exc.strerror or exc}"]) from None
    if len(raw) > MAX_DOCUMENT_BYTES:
        raise ConfigError([f"{p}: larger than {MAX_DOCUMENT_BYTES:,} bytes; a procedure or configuration is a "
                           "few kB"])
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError([f"{p}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}); "
                           "save the file as UTF-8"]) from None


def load_model(model: type[M], path: str | Path) -> tuple[M, str]:
    """Read a YAML file into `model`; returns the model and the file's text."""
    text = read_text(path)
    data, positions = load_yaml(text, str(path))
    return validate(model, data, positions, str(path)), text
