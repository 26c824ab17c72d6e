"""Help rules of every ``presim`` command (issue 45): one default style, every default stated (seeds
too), a description on every command, the shared options described once in ``presim --help``."""

from __future__ import annotations

import argparse
import re

import pytest

from presim.cli import COMMON_OPTIONS_HELP, build_parser


def _commands(parser: argparse.ArgumentParser, prefix: str = "presim"):
    """``(name, parser)`` of every (nested) sub-command."""
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, p in a.choices.items():
                yield f"{prefix} {name}", p
                yield from _commands(p, f"{prefix} {name}")


COMMANDS = list(_commands(build_parser()))


def _option_helps(p: argparse.ArgumentParser) -> dict[str, str]:
    """Each option's help line as ``--help`` prints it (its default filled in)."""
    fmt = p._get_formatter()
    return {a.option_strings[-1]: fmt._expand_help(a) for a in p._actions
            if a.option_strings and a.help not in (None, argparse.SUPPRESS)}


def test_walks_every_command():
    names = {n for n, _ in COMMANDS}
    assert {"presim drive", "presim view", "presim sim2real depth", "presim demo"} <= names
    assert len(names) >= 20


@pytest.mark.parametrize("name,p", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_help_rules(name, p, capsys):
    with pytest.raises(SystemExit) as e:
        p.parse_args(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert p.description and len(p.description) > 20, f"{name}: no description"
    assert text.count("$PRESIM_MAX_MEMORY") == 0, f"{name}: the long --max-memory text belongs to `presim --help`"
    helps = _option_helps(p)
    leaf = not any(isinstance(a, argparse._SubParsersAction) for a in p._actions)
    for opt, h in helps.items():
        # One style: "default: X" (or a choice marked "(default)"), never "(default X" / "default X)".
        assert not re.search(r"[(;,] ?default [^\s(]", h), f"{name} {opt}: default not written 'default: X': {h}"
        a = next(a for a in p._actions if opt in a.option_strings)
        if a.default is not None and a.default is not False and a.default is not argparse.SUPPRESS:
            assert re.search(r"\bdefault\b", h), f"{name} {opt}: default {a.default!r} not stated: {h}"
        if "seed" in opt:
            assert re.search(r"default: [\d\[]", h), f"{name} {opt}: seed default not stated: {h}"
        if opt in ("--max-memory", "--quiet"):
            assert len(h) <= 40, f"{name} {opt}: one short line, the full text is in `presim --help`"
    if leaf:
        assert "--max-memory" in helps and "--quiet" in helps, f"{name}: common options missing"


def test_common_options_described_once(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    out = capsys.readouterr().out
    assert COMMON_OPTIONS_HELP.splitlines()[1].strip() in out and out.count("$PRESIM_MAX_MEMORY") == 1
