"""Where paths go, off the tape: the counter-based random numbers (``random``), the
emitters' table (``emitters``), the directions and densities (``sampling``), the scene read
as tables (``tables``), the continuous choices at a vertex compiled by ``minidiff.compile``
(``choices``), and the sampler that records every decision as constants (``tracer``)."""
