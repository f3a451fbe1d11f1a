"""The path integrator: light that bounces, by Monte Carlo (``render(..., integrator="path")``).

Like the direct renderer, it makes its discrete choices off the tape and recomputes
everything continuous on it. Its folders are its concerns, each importing only from the
ones before it:

* ``sample/``: where each path goes, off the tape (the BVH of ``render.trace``; directions
  and densities from ``sampling``, points on area lights from ``emitters``, counter-based
  random numbers from ``random``: the same seed, the same image; the choices at a vertex
  compiled by ``minidiff.compile`` in ``choices``), recorded as constants by ``tracer``;
* ``gradient/``: what each path carries, on the tape (``transport``: every vertex
  recomputed from its primitive by ``render.shade.surface.surface_at``, the direct
  renderer's surfaces too, shaded with ``render.shade.lighting``'s materials and lights),
  the gradient of whole paths compiled from those formulas (``window``), and path replay
  one depth at a time on the tape for what does not compile (``replay``);
* ``twin/``: the hand-written Numba twin of the sampler and of the radiance's value
  (``kernel``, with ``scalar``, ``packed``): the image and the records, fast, until the
  traced kernels replace it;
* ``boundary/``: primary visibility's boundary term (``primary``: ``antialias="boundary"``
  or ``"primary"``, the boundary integral of ``render.edges`` with the jumps
  path-traced) and secondary visibility's (``secondary``: ``"boundary"`` or
  ``"secondary"``; soft shadows, lights' shadows, indirect occlusion, by edge sampling
  from every path vertex, with the curves and their draws in ``silhouettes``);
* ``integrator``: the image from batches of paths, and its gradient through the tape or by
  replay (``render_path``, ``replay_gradient``), choosing among the above.

``docs/path_tracing.md`` walks through them."""

from render.path.integrator import render_path, replay_gradient

__all__ = ["render_path", "replay_gradient"]
