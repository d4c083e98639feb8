"""The ``mmada-rl`` command line: every sub-command explains itself."""
from __future__ import annotations

import pytest

from mmada_rl.cli import build_parser, main

SUBCOMMANDS = ("doctor", "collect", "merge", "info", "import-h5", "fit-tokenizers", "quickstart", "eval")


def test_top_level_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for name in SUBCOMMANDS:
        assert name in text


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_subcommand_help(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([name, "--help"])
    assert exit_.value.code == 0
    assert "usage: mmada-rl " + name in capsys.readouterr().out


def test_no_subcommand_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_collect_rejects_an_unknown_policy(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", "x", "--policy", "magic"])
    assert exit_.value.code == 2
    assert "invalid choice: 'magic'" in capsys.readouterr().err
