"""Test-wide settings: float64 is enabled so references can be compared to 1e-9 and better.

Library code is dtype-preserving, so float32 paths are still exercised by passing float32 inputs.
"""

from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

SHARED = Path(__file__).resolve().parents[2] / "shared"
