"""dpc_jax.runtime.machine: the CPU line of the benchmarks' headers and the studies' records, from
/proc/cpuinfo texts."""

from __future__ import annotations

from dpc_jax.runtime.machine import cpu_description, this_cpu

# Two processors of a 2-core x86 machine, as the kernel prints them (trimmed).
X86 = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
flags\t\t: fpu vme sse sse2 avx avx2 avx512f avx512bw

processor\t: 1
vendor_id\t: AuthenticAMD
cpu family\t: 99
model\t\t: 99
model name\t: another name
flags\t\t: fpu
"""

ARM = """processor\t: 0
BogoMIPS\t: 243.75
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics
CPU implementer\t: 0x41
"""


def test_x86_names_the_first_processor_its_family_model_and_widest_vector_unit() -> None:
    assert cpu_description(X86, 2, "x86_64") == "AMD EPYC (family 25, model 17, AVX-512), 2 CPUs"


def test_avx2_without_avx512() -> None:
    text = X86.replace(" avx512f avx512bw", "")
    assert cpu_description(text, 4, "x86_64") == "AMD EPYC (family 25, model 17, AVX2), 4 CPUs"


def test_arm_without_a_model_name_falls_back_to_the_architecture() -> None:
    assert cpu_description(ARM, 8, "aarch64") == "aarch64 (NEON), 8 CPUs"


def test_no_cpuinfo_gives_the_architecture_and_an_unknown_count() -> None:
    assert cpu_description("", None, "arm64") == "arm64, ? CPUs"


def test_this_machine_is_described_in_one_line() -> None:
    line = this_cpu()
    assert "\n" not in line and line.endswith(" CPUs")
