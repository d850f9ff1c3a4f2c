"""End-to-end pipelines: the synthetic demo and the papers' experiment protocol.

Imported by the command line and by ``experiments/`` only.
"""
