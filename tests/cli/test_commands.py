"""The command line from one table (cli/commands.py): the parser takes what the table declares and
nothing else, the settings come from jitdyn.settings, and the manual lists the same options."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from jitdyn.cli.commands import COMMANDS, Command, OneOf, reference
from jitdyn.cli.main import build_parser, main
from jitdyn.settings import settings_for

ROOT = Path(__file__).resolve().parents[2]


def _leaves(
    command: Command, path: tuple[str, ...], group: str
) -> Iterator[tuple[tuple[str, ...], Command, str]]:
    if command.actions:
        for action in command.actions:
            yield from _leaves(action, (*path, action.name), group)
    elif not command.passthrough:
        yield path, command, group


def _parser_at(parser: argparse.ArgumentParser, path: tuple[str, ...]) -> argparse.ArgumentParser:
    for name in path:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return parser


LEAVES = [leaf for command in COMMANDS for leaf in _leaves(command, (command.name,), command.name)]


@pytest.mark.parametrize("path, command, group", LEAVES, ids=[" ".join(p) for p, _, _ in LEAVES])
def test_each_command_takes_its_table_row_and_its_settings_and_nothing_else(
    path: tuple[str, ...], command: Command, group: str
) -> None:
    parser = _parser_at(build_parser(), path)
    taken = {
        flag
        for action in parser._actions
        if not isinstance(action, argparse._SubParsersAction)
        for flag in (action.option_strings or [action.dest])
    }
    declared = {
        flag if flag.startswith("-") else one.kwargs.get("dest", flag)
        for entry in command.options
        for one in (entry.options if isinstance(entry, OneOf) else (entry,))
        for flag in one.flags
    }
    settings = {s.flag for s in settings_for(group)}
    assert taken == declared | settings | {"-h", "--help", "-v", "--verbose"}


def test_the_manual_lists_every_commands_options() -> None:
    manual = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert reference() in manual, "docs/cli.md: paste jitdyn.cli.commands.reference() anew"
    for path, command, _ in LEAVES:
        assert f"### `jitdyn {' '.join(path)}`" in manual


def test_an_option_of_the_table_parses_and_checks_as_declared(capsys: pytest.CaptureFixture[str]) -> None:
    """A value the table's type refuses is a one-line usage error naming the option (exit 2)."""
    with pytest.raises(SystemExit) as exit_:
        main(["demo", "--loss", "1.5"])
    assert exit_.value.code == 2
    assert "argument --loss: expected a probability in [0, 1], got '1.5'" in capsys.readouterr().err
    args = build_parser().parse_args(["demo", "--loss", "5%", "--clock", "LockStep", "--seconds", "2500ms"])
    assert (args.loss, args.clock.name, args.seconds) == (0.05, "LOCKSTEP", 2.5)


def test_replay_names_the_formats_it_reads() -> None:
    from jitdyn.cli.commands import TRIAL_FORMATS
    from jitdyn.cli.trials import FORMATS

    assert TRIAL_FORMATS == tuple(FORMATS)
