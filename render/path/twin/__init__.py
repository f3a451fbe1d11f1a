"""The hand-written Numba twin of the sampler and the transport (kept, with the measured
reason in ``docs/architecture.md``, until the traced kernels replace it): the scene as plain
arrays (``packed``), the per-path arithmetic (``scalar``), whole paths in parallel
(``kernel``), and the compiled replay of materials, lights' strengths and the environment
(``chain``, ``adjoint``)."""
