"""Step 1, the discrete decisions, on plain arrays (no tape): which primitive each ray hits
and which lights each hit sees.

* ``visibility``: runs them for a render (``trace_visibility``: camera rays, then a shadow
  ray per hit and light, the light saying where its rays go), reusing cached results;
* ``accel`` (the ray-tracing front end), ``bvh`` and ``intersect`` (its tree and kernels),
  ``raster`` (camera rays by rasterising, the same hits), ``light_view`` (many shadow rays
  towards a point light answered in its view), ``primitives`` (the scene as id-numbered
  triangles and spheres);
* ``topology`` and ``seams``: mesh edges, their faces, and the edges meshes share (for the
  edge terms).
"""
