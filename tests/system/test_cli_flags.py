"""Every flag of every command says what it does, and an output goes by one name on every command (the old name
still accepted)."""

from __future__ import annotations

import argparse

import pytest

from occvo_cli.cli import build_parser


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_every_flag_and_argument_has_help():
    missing = [
        f"{name} {a.option_strings or a.dest}"
        for name, p in _commands().items()
        for a in p._actions
        if not a.help or a.help == argparse.SUPPRESS and a.dest != "debug"
    ]
    assert not missing, missing


def test_the_output_flag_is_out_everywhere_and_output_still_works():
    commands = _commands()
    writers = {n for n, p in commands.items() for a in p._actions if "--out" in a.option_strings}
    assert {"run", "train-occ", "ablation", "eval-occ", "replay", "tile"} <= writers
    for name, p in commands.items():
        for a in p._actions:
            if "--output" in a.option_strings:
                assert "--out" in a.option_strings and a.dest == "out", name


@pytest.mark.parametrize("flag", ["--out", "--output"])
def test_replay_takes_either_spelling(flag):
    args = build_parser().parse_args(["replay", "synthetic:0", flag, "t.tum"])
    assert args.out == "t.tum"
