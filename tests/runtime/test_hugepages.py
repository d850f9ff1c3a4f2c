"""dpc_jax.runtime.hugepages: the re-executed process has the tunable; the opt-out and no-op cases."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from dpc_jax.runtime import hugepages

SCRIPT = (
    "import os, sys; from dpc_jax.runtime.hugepages import reexec_with_huge_pages; "
    "print('start', flush=True); reexec_with_huge_pages(); "
    "print(os.environ.get('GLIBC_TUNABLES'), sys.argv[1:])"
)


def _run(env_updates: dict[str, str]) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", hugepages.OPT_OUT)}
    env.update(env_updates)
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, "a b", "--x"], capture_output=True, text=True, env=env, check=True
    )
    return done.stdout.splitlines()


def _supported() -> bool:
    return (
        sys.platform.startswith("linux")
        and hugepages._glibc_supports_tunable()
        and hugepages._thp_available()
    )


@pytest.mark.skipif(not _supported(), reason="needs Linux, glibc >= 2.35 and transparent huge pages")
def test_reexec_adds_the_tunable_and_keeps_arguments() -> None:
    # "start" twice: the command ran again from the beginning, with the same arguments.
    assert _run({}) == ["start", "start", "glibc.malloc.hugetlb=1 ['a b', '--x']"]
    kept = _run({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"})
    assert kept[-1] == "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1 ['a b', '--x']"


def test_no_reexec_when_opted_out_or_already_set() -> None:
    assert _run({hugepages.OPT_OUT: "0"}) == ["start", "None ['a b', '--x']"]
    assert _run({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}) == [
        "start",
        "glibc.malloc.hugetlb=1 ['a b', '--x']",
    ]


def test_glibc_version_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    for libc, expected in [
        (("glibc", "2.35"), True),
        (("glibc", "2.34"), False),
        (("glibc", "3.0"), True),
        (("", ""), False),
        (("glibc", "weird"), False),
    ]:
        monkeypatch.setattr(platform, "libc_ver", lambda libc=libc: libc)
        assert hugepages._glibc_supports_tunable() is expected, libc
