"""The process around the library: how a long loop reports progress (``progress``), JAX's
persistent compilation cache for the command line (``compilation_cache``), glibc's transparent
huge pages for XLA's CPU buffers (``hugepages``), the lazy re-exports of the package faces
(``lazy``), the description of the CPU a measurement ran on (``machine``) and the versions of the
libraries it ran with (``versions``).

Nothing here imports JAX or the rest of the package: every layer may use it, and
``compilation_cache`` and ``hugepages`` must act before JAX is imported.
"""
