"""Test-wide settings: float64 is enabled so references can be compared to 1e-9 and better, and the
command line's persistent compilation cache is off.

Library code is dtype-preserving, so float32 paths are still exercised by passing float32 inputs.
"""

import os
from pathlib import Path

import jax

from dpc_jax.compilation_cache import OPT_OUT

# The `dpc-jax` processes the tests start would keep their compiled programs in the user's cache
# folder: the tests leave it alone (those of the cache itself choose a temporary folder).
os.environ[OPT_OUT] = "0"

jax.config.update("jax_enable_x64", True)

SHARED = Path(__file__).resolve().parents[2] / "shared"
