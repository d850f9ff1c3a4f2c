"""``this_cpu`` where ``experiments/studies/detection_limit.py`` still imports it from (through
``sys.path``); every other script imports it from ``dpc_jax.runtime.machine``. Goes when that study
takes the experiment kit's stamp (``dpc_jax.experiments.stamp``)."""

from dpc_jax.runtime.machine import this_cpu

__all__ = ["this_cpu"]
