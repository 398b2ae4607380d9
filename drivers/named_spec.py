"""An instrument description (a chamber's register map, a table's command language) given by name or as a
mapping: a shipped one, a shipped one with some keys changed (`base: NAME`), or a whole custom one."""

from collections.abc import Mapping, Sequence
from dataclasses import fields
from typing import Any, TypeVar

T = TypeVar("T")


def from_spec(spec: str | Mapping[str, Any] | T, shipped: Mapping[str, T], cls: type[T], what: str, *,
              merged: Sequence[str] = (), pairs: Sequence[str] = ()) -> T:
    """`spec` as a `cls` (a dataclass). `merged`: mapping fields a `base:` override merges key by key;
    `pairs`: fields given as a YAML list and held as a tuple of floats. Problems raise ValueError naming
    `what` ("chamber profile", "table language")."""
    if isinstance(spec, cls):
        return spec
    if isinstance(spec, str):
        try:
            return shipped[spec]
        except KeyError:
            raise ValueError(f"unknown {what} {spec!r}; known: {', '.join(shipped)}") from None
    names = [f.name for f in fields(cls)]  # type: ignore[arg-type]  # cls is a dataclass
    data = dict(spec)  # type: ignore[arg-type]
    base = data.pop("base", None)
    if base is not None:
        start = {name: getattr(from_spec(base, shipped, cls, what), name) for name in names}
        for key in merged:
            if isinstance(data.get(key), Mapping):
                data[key] = {**start[key], **data[key]}
        data = {**start, **data}
    unknown = set(data) - set(names)
    if unknown:
        raise ValueError(f"{what}: unknown key(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(names))}")
    for key in pairs:
        if data.get(key) is not None:
            data[key] = tuple(float(v) for v in data[key])
    try:
        return cls(**data)
    except TypeError as exc:
        raise ValueError(f"{what}: {exc}") from None
