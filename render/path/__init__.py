"""The path integrator: light that bounces, by Monte Carlo (``render(..., integrator="path")``).

``random`` (counter-based random numbers: the same seed, the same image), ``sampling``
(directions and points and their densities), ``emitters`` (area lights), ``tracer`` (off
the tape: the paths' discrete choices, traced with the BVH), ``transport`` (on the tape:
what each path carries), ``integrator`` (the image, and its gradient through the tape or
by replay). ``docs/path_tracing.md`` walks through them.
"""

from render.path.integrator import render_path, replay_gradient

__all__ = ["render_path", "replay_gradient"]
