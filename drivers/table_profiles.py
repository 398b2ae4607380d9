"""Rate-table command languages as data: a vendor's language is a profile, not new code.

A `TableLanguage` says how each operation the `RateTable` protocol needs is spelled on the
wire: command templates (`JOG{rate:+.4f}`), the suffix that turns a command into a query
(Ideal Aerosmith: `?`), the line terminator, the reply of each query as a template
(`PVE {rate:+.5f}`), the acknowledgement of an action and the error reply. Templates use
Python's format syntax; a field with a numeric format (`:+.4f`, `:d`, `:g`) parses as a
number, any other as text. The driver (`rate_table.SerialRateTable`) formats commands and
parses replies from it; the simulated table (`sims/table_server.py`) does the reverse from the
same profile, so a profile is tested against the driver that will use it.

A profile is a mapping in a lab configuration (`table: {driver: serial_table, language:
{base: ideal_aerosmith, terminator: "\\r"}}`) or one of `LANGUAGES`.
"""

from __future__ import annotations

import re
import string
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

from .named_spec import from_spec

_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_NUMERIC_SPECS = "bcdeEfFgGnoxX%"
# Operations the RateTable protocol needs; a profile spells each or leaves it out (None).
ACTIONS = ("jog", "stop", "enable", "home")
QUERIES = ("identity", "limits", "velocity", "status", "position")
# The fields each query's reply template may hold.
REPLY_FIELDS = {"identity": {"vendor", "model", "serial"}, "limits": {"max_rate", "accel"}, "velocity": {"rate"},
                "status": {"mode", "state"}, "position": {"deg"}}


def template_regex(template: str) -> re.Pattern[str]:
    """The regex that parses what `template` formats: numeric fields as numbers, others as text."""
    parts = []
    for literal, name, spec, _conv in string.Formatter().parse(template):
        parts.append(re.escape(literal))
        if name is None:
            continue
        if not name.isidentifier():
            raise ValueError(f"template {template!r}: field {name!r} must be a name")
        numeric = bool(spec) and str(spec)[-1] in _NUMERIC_SPECS
        parts.append(f"(?P<{name}>{_NUMBER})" if numeric else f"(?P<{name}>.*?)")
    return re.compile("^" + "".join(parts) + "$")


def template_fields(template: str) -> set[str]:
    return {name for _lit, name, _spec, _conv in string.Formatter().parse(template) if name}


@dataclass(frozen=True)
class TableLanguage:
    name: str
    commands: dict[str, str | None]  # action -> command template (jog needs {rate}); None: not in the language
    queries: dict[str, str | None]  # query -> command it sends, before `query_suffix`; None: not in the language
    replies: dict[str, str]  # query -> reply template
    ack: str = "OK"  # what an action answers (a template without fields; "" an empty line)
    error: str | None = None  # an error reply's template ({code}, {text}); None: the language has none
    query_suffix: str = ""
    terminator: str = "\r\n"  # ends every command and every reply
    status_modes: dict[str, str] = field(default_factory=lambda: {"JOG": "JOG", "STOP": "STOP", "FAULT": "FAULT"})
    settled_state: str = "SETTLED"  # the status `state` that means "at the commanded rate"
    # Without a status query the driver judges settling from the velocity: within this fraction of
    # the commanded rate, plus settle_floor_dps.
    settle_fraction: float = 1e-3
    settle_floor_dps: float = 0.01
    vendor: str = ""  # the identity when the language has no identity query
    model: str = ""
    fixed_limits: tuple[float, float] | None = None  # (max rate deg/s, accel deg/s^2) without a limits query

    def __post_init__(self) -> None:
        where = f"table language {self.name!r}"
        unknown = (set(self.commands) - set(ACTIONS)) | (set(self.queries) - set(QUERIES))
        if unknown:
            raise ValueError(f"{where}: unknown operation(s) {', '.join(sorted(unknown))}; known: "
                             f"{', '.join(ACTIONS + QUERIES)}")
        for op in ("jog", "stop"):
            if not self.commands.get(op):
                raise ValueError(f"{where}: needs a {op!r} command")
        if not self.queries.get("velocity"):
            raise ValueError(f"{where}: needs a 'velocity' query")
        if "rate" not in template_fields(self.commands["jog"] or ""):
            raise ValueError(f"{where}: the jog command needs a {{rate}} field, e.g. 'JOG {{rate:.4f}}'")
        for query, command in self.queries.items():
            if command is None:
                continue
            reply = self.replies.get(query)
            if reply is None:
                raise ValueError(f"{where}: query {query!r} has no reply template")
            extra = template_fields(reply) - REPLY_FIELDS[query]
            if extra:
                raise ValueError(f"{where}: reply of {query!r} has unknown field(s) {', '.join(sorted(extra))}; "
                                 f"allowed: {', '.join(sorted(REPLY_FIELDS[query]))}")
            template_regex(reply)
        if self.error is not None:
            template_regex(self.error)
        if not self.terminator:
            raise ValueError(f"{where}: terminator must not be empty")

    @property
    def terminator_bytes(self) -> bytes:
        return self.terminator.encode("ascii")

    def has(self, operation: str) -> bool:
        return bool(self.commands.get(operation) or self.queries.get(operation))

    def action(self, operation: str, **values: float) -> str:
        """The command line (without terminator) of an action."""
        template = self.commands.get(operation)
        if not template:
            raise ValueError(f"table language {self.name!r} has no {operation!r} command")
        return template.format(**values)

    def query(self, operation: str) -> str:
        command = self.queries.get(operation)
        if not command:
            raise ValueError(f"table language {self.name!r} has no {operation!r} query")
        return command + self.query_suffix

    @cached_property
    def reply_patterns(self) -> dict[str, re.Pattern[str]]:
        return {q: template_regex(self.replies[q]) for q, c in self.queries.items() if c}

    @cached_property
    def ack_pattern(self) -> re.Pattern[str]:
        return template_regex(self.ack)

    @cached_property
    def error_pattern(self) -> re.Pattern[str] | None:
        return template_regex(self.error) if self.error is not None else None

    @cached_property
    def command_patterns(self) -> dict[str, re.Pattern[str]]:
        """What the simulated table parses: each action's and query's line."""
        out = {op: template_regex(t) for op, t in self.commands.items() if t}
        out.update({q: re.compile("^" + re.escape(self.query(q)) + "$") for q, c in self.queries.items() if c})
        return out


LANGUAGES: dict[str, TableLanguage] = {
    # labrunner's own ASCII language (docs/design.md, "Instruments"): three-letter commands, CR LF,
    # every command answered by one line, errors as `ERR <code> <text>`.
    "labrunner": TableLanguage(
        name="labrunner",
        commands={"jog": "JOG{rate:+.4f}", "stop": "STO"},
        queries={"identity": "IDN", "limits": "LIM", "velocity": "PVE", "status": "STA"},
        replies={"identity": "IDN {vendor},{model},{serial}", "limits": "LIM {max_rate:.1f} {accel:.1f}",
                 "velocity": "PVE {rate:+.5f}", "status": "STA {mode} {state}"},
        ack="OK", error="ERR {code:d} {text}",
    ),
    # Ideal Aerosmith table language (ACL), written from the public sources found:
    # - the command table of a public Python client for Ideal Aerosmith tables (package `aerosmith`,
    #   a module headed "Ideal Aerosmith Table Language"; its repository was not identified):
    #   action commands HOM (home), ACL (acceleration), CAL, CLU (clutch 1..5), JOG (rate, deg/s,
    #   negative counter-clockwise, -360..360 on that table), SRV (servo/motor 0/1), STO (stop);
    #   "query commands are denoted by the use of a ? after the command"; "action commands ...
    #   will always return AeroSmith's response terminator".
    # - an IMU test suite's README for an Ideal Aerosmith single-axis table (GitHub, "GM IMU
    #   Validation Test Suite"): HOM, STO, PPO (position query), 9600 baud.
    # Open in those sources, and chosen here (check against your table's manual):
    # - the terminator: CR LF is assumed for commands and replies;
    # - the separator between a command and its argument: one space (`JOG 12.5000`);
    # - the velocity query: `JOG?` (the query form of JOG, by the '?' rule) answering the measured
    #   rate as a bare number; `PPO?` answers the position in degrees as a bare number;
    # - an action's acknowledgement: an empty line (the bare response terminator);
    # - identity, limits, status and error replies: none is documented there, so the identity and
    #   limits are this profile's constants and settling is judged from the velocity;
    # - `SRV 1` (servo on) is sent once per connection before the first jog.
    "ideal_aerosmith": TableLanguage(
        name="ideal_aerosmith",
        commands={"jog": "JOG {rate:.4f}", "stop": "STO", "enable": "SRV 1", "home": "HOM"},
        queries={"velocity": "JOG", "position": "PPO"},
        replies={"velocity": "{rate:.4f}", "position": "{deg:.4f}"},
        ack="", error=None, query_suffix="?", terminator="\r\n",
        vendor="Ideal Aerosmith", model="rate table (ACL)", fixed_limits=(360.0, 100.0),
    ),
}


def language_from(spec: str | Mapping[str, Any] | TableLanguage) -> TableLanguage:
    """A language by name, or from a mapping (`{base: NAME, ...}` overrides a shipped one)."""
    return from_spec(spec, LANGUAGES, TableLanguage, "table language",
                     merged=("commands", "queries", "replies", "status_modes"), pairs=("fixed_limits",))


__all__ = ["LANGUAGES", "TableLanguage", "language_from", "template_fields", "template_regex"]
