"""The command line: every subcommand's help renders (config help strings may hold '%')."""

from __future__ import annotations

import pytest

from gsmn.cli import build_parser

COMMANDS = [["world"], ["eval"], ["fit-avg-forward"], ["collect"], ["train", "supervised"], ["train", "dagger"],
            ["serve"]]


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c))
def test_help_renders(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([*command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: gsmn " + " ".join(command))
    if command[0] in ("eval", "collect", "train"):
        assert "--train.batch-size" in out
