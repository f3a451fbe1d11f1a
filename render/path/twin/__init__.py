"""The hand-written Numba twin of the sampler and the transport's value (kept, with the
measured reason in ``docs/architecture.md``, as the fastest primal and the writer of the
records the compiled gradient reads): the scene as plain arrays (``packed``), the per-path
arithmetic (``scalar``), whole paths in parallel (``kernel``). No derivative is written
here: the gradient is ``render.path.gradient.window``'s, compiled from the readable
formulas."""
