"""`--help` teaches (issue 14, item 5): every sub-command has a description for users and an example, every
argument has help, defaults are shown, and one concept has one metavar across the commands."""

from __future__ import annotations

import argparse
import re

import pytest

from labrunner.cli import build_parser, main, subparsers

PARSER = build_parser()
COMMANDS = dict(subparsers(PARSER))

# Concepts with more than one spelling: options (or positionals, by dest) that must share a metavar.
SAME_CONCEPT = (
    ("db", "--db"),  # `status DB` and `run --db DB`
    ("procedure",),
    ("data",),  # a campaign CSV or a database
    ("--lab", "--lab-config"),
    ("--sim-config", "--config"),
    ("--csv", "--json", "--model"),  # files written or read
    ("--out", "--report", "--fit-out"),  # directories
    ("--campaign", "--seed", "--faults", "--events"),  # counts and ids
    ("--watch", "--wait", "--duration"),  # seconds
    ("--chamber-port", "--table-port", "--imu-port"),
)
# The vocabulary: upper-case words, or a file kind named by its extension.
METAVAR = re.compile(r"^(?:[A-Z][A-Z0-9_]*|[A-Z]+\.yaml)$")


def _arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction))]


def _key(action: argparse.Action) -> str:
    return action.option_strings[-1] if action.option_strings else action.dest


def test_every_command_is_walked() -> None:
    names = set(COMMANDS)
    assert {"run", "resume", "status", "abort", "export", "check", "fit", "diagnose", "sim", "sim serve"} <= names
    # `labrunner COMMAND --help` is the parser walked: the walk names commands as they are typed.
    assert COMMANDS["sim serve"].prog == "labrunner sim serve"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_description_and_example(name: str) -> None:
    parser = COMMANDS[name]
    assert parser.description and len(parser.description.split()) >= 8, f"{name}: no description for users"
    examples = re.findall(rf"^  labrunner {re.escape(name)}\b.*$", parser.epilog or "", re.M)
    if name == "sim":  # a group: its example is its one command's
        examples = re.findall(r"^  labrunner sim serve\b.*$", parser.epilog or "", re.M)
    assert examples, f"{name}: no example (an indented `labrunner {name} ...` line in the epilog)"
    assert parser.format_help().count("\n  labrunner ") >= len(examples)  # kept as written, not re-wrapped


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_argument_has_help_and_a_metavar(name: str) -> None:
    for action in _arguments(COMMANDS[name]):
        assert action.help and action.help is not argparse.SUPPRESS, f"{name} {_key(action)}: no help"
        if action.nargs == 0 or action.choices:  # flags; choices show themselves
            continue
        assert action.metavar, f"{name} {_key(action)}: no metavar (argparse would print {action.dest.upper()})"
        assert METAVAR.match(str(action.metavar)), f"{name} {_key(action)}: metavar {action.metavar!r}"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_defaults_are_shown(name: str) -> None:
    parser = COMMANDS[name]
    text = "".join(parser.format_help().split())  # no white space: wrapping may break after a hyphen
    for action in _arguments(parser):
        if action.nargs == 0 or action.default is None or action.required:
            continue
        shown = parser._get_formatter()._expand_help(action)
        assert "default" in shown, f"{name} {_key(action)}: default {action.default!r} not shown"
        assert "".join(shown.split()) in text


def test_one_concept_one_metavar() -> None:
    seen: dict[str, set[str]] = {}
    for name, parser in COMMANDS.items():
        for action in _arguments(parser):
            if action.metavar:
                seen.setdefault(_key(action), set()).add(f"{action.metavar} ({name})")
    for group in SAME_CONCEPT:
        used = {m.split(" (")[0]: m for key in group for m in seen.get(key, ())}
        assert len(used) <= 1, f"{group}: one concept, several metavars: {sorted(used.values())}"
    for key, metavars in seen.items():
        assert len({m.split(" (")[0] for m in metavars}) == 1, f"{key}: {sorted(metavars)}"


def test_top_level_help_has_examples_and_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert "\n  labrunner run quick --sim --db quick.db" in out
    assert "exit codes: 0 done, 3 paused, 4 aborted" in " ".join(out.split())
    assert "one sub-command per module" not in out  # developer text stays in the code


def test_a_defaults_line_names_the_value(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["status", "--help"])
    assert "how many recent events to show (default: 8)" in " ".join(capsys.readouterr().out.split())
