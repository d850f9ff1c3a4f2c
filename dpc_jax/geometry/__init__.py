"""Geometry: SO(3)/SE(3), the pinhole camera, image warps, SSIM, pose corrections and pose algebra.

Pure math (``jnp`` and numpy); imports nothing else from the package.
"""
