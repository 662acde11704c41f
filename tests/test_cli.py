"""The ``dcsc`` command dispatches to the recipes and leaves their help to them."""

from __future__ import annotations

import pytest

from dcsc_torchrl.cli import main


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["run", "lunarlander", "--help"], "--methods"),
        (["pretrain", "uav", "--help"], "--resume"),
        (["reproduce", "--help"], "--quick"),
    ],
)
def test_subcommand_help_is_the_recipes_own(argv, expected, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 0
    assert expected in capsys.readouterr().out


def test_unknown_task_is_refused_with_the_choices(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["pretrain", "mars"])
    assert exit_info.value.code == 2
    assert "lunarlander" in capsys.readouterr().err


def test_play_without_checkpoint_says_how_to_get_one(tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        main(["play", "lunarlander", "--checkpoint", str(tmp_path / "missing.pt")])
    assert "dcsc pretrain lunarlander" in str(exit_info.value.code)
