"""dpc_jax: self-supervised deep pose correction of classical stereo visual odometry."""

__version__ = "0.1.0"
