"""dpc_jax.runtime.versions: the versions stamped beside figures are those of the modules that ran.

The reference is each module's own ``__version__`` (what the imported code says of itself), not the
package metadata the function reads.
"""

from __future__ import annotations

import platform
import subprocess
import sys

import cv2
import flax
import jax
import jaxlib
import numpy as np

from dpc_jax.runtime.machine import this_cpu
from dpc_jax.runtime.versions import library_versions, versions_line


def test_the_versions_are_those_of_the_imported_modules() -> None:
    found = library_versions()
    assert found["python"] == platform.python_version()
    assert (found["jax"], found["jaxlib"], found["flax"], found["numpy"]) == (
        jax.__version__, jaxlib.__version__, flax.__version__, np.__version__)
    # OpenCV's wheels add a build number to the library's own version: 5.1.0.95 for cv2 5.1.0.
    assert found["opencv"].startswith(cv2.__version__ + ".")
    assert versions_line() == ", ".join(
        f"{'Python' if k == 'python' else k} {v}" for k, v in found.items())


def test_the_version_option_prints_them_with_the_cpu() -> None:
    shown = subprocess.run([sys.executable, "-m", "dpc_jax", "--version"], capture_output=True, text=True,
                           check=True).stdout.splitlines()
    assert shown[0].startswith("dpc-jax ") and shown[1:] == [versions_line(), this_cpu()]
