"""The networks: their input (``Batch``) and outputs, the convolutions, the models and the losses.

Imports :mod:`dpc_jax.geometry` only.
"""
