"""The tests' own XLA flags: a flag the installed XLA does not know is left out, not passed to it (XLA
aborts a process on one)."""

from __future__ import annotations

import pytest
import support


def test_a_flag_this_xla_does_not_know_is_left_out(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(support._CHOSEN_FLAGS)  # as in a fresh session: the flags are tried again
    monkeypatch.setattr(support, "_FAST_CODE_GENERATION",
                        ("--xla_backend_optimization_level=0", "--xla_cpu_no_such_flag_anywhere=true"))
    assert support._test_xla_flags() == "--xla_backend_optimization_level=0"
