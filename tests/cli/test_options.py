"""Options every command shares: a script may pass them to each command alike (issue 61, case 15)."""

from __future__ import annotations

import pytest

from dpc_jax.cli import _subcommands, build_parser


@pytest.mark.parametrize("command", _subcommands())
def test_every_command_takes_no_progress(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args([command, "--help"])
    assert done.value.code == 0
    assert "--no-progress" in capsys.readouterr().out
