"""The path integrator: light that bounces, by Monte Carlo (``render(..., integrator="path")``).

Like the direct renderer, it makes its discrete choices off the tape and recomputes
everything continuous on it:

* ``tracer``: where each path goes, off the tape (the BVH of ``render.trace``; directions
  and densities from ``sampling``, points on area lights from ``emitters``, counter-based
  random numbers from ``random``: the same seed, the same image), recorded as constants;
* ``transport``: what each path carries, on the tape: every vertex recomputed from its
  primitive by ``render.shade.surface.surface_at`` (the direct renderer's surfaces too),
  shaded with ``render.shade.lighting``'s materials and lights;
* ``integrator``: the image from batches of paths, and its gradient through the tape or by
  replay (``render_path``, ``replay_gradient``);
* ``edges``: primary visibility's boundary term (``antialias="boundary"`` or
  ``"primary"``), the boundary integral of ``render.edges`` with the jumps path-traced;
* ``secondary``: secondary visibility's (``"boundary"`` or ``"secondary"``): soft shadows,
  lights' shadows, indirect occlusion, by edge sampling from every path vertex, with the
  curves and their draws in ``silhouettes``;
* ``kernel`` (with ``scalar``, ``packed``, ``chain``, ``adjoint``, ``replay``): the
  compiled path tracer and path replay beside the reference; ``window``: the replay's
  windows, ``transport``'s formulas for one path compiled by ``minidiff.compile``.

``docs/path_tracing.md`` walks through them.
"""

from render.path.integrator import render_path, replay_gradient

__all__ = ["render_path", "replay_gradient"]
