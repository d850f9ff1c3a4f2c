import sys

from dpc_jax.cli import main

sys.exit(main())
