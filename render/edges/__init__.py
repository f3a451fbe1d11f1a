"""Step 4, moving edges: the derivative that visibility's jumps contribute, two ways.

``terms`` is the entry point (the renderer calls ``add_edge_terms`` with
``antialias=True`` and ``add_boundary_term`` with ``antialias="boundary"``).

* Pixel pairs (``antialias=True``): pairs of adjacent samples across a silhouette or crease
  (``silhouettes``) or a shadow edge (``shadows``) are found on plain arrays; on the tape,
  where the edge crosses each pair and the blend of the two samples by box coverage.
  ``geometry`` holds what both share (the sample grid, edge functions, crossings, box
  coverage).
* The boundary integral (``antialias="boundary"``, the ``boundary`` package): the exact
  derivative of box-filtered pixels, an integral along every curve where the image jumps,
  organised by curve kind: mesh edges (silhouettes, creases, seams), the crossings of
  surfaces, sphere outlines, the cuts of triangles through spheres, shadow borders. Each
  kind finds its curves, weighs its quadrature points off the tape and writes its edge
  function on the tape; the term loops over the kinds. Beside it, ``interior`` gives the
  pixels one sample cannot stand for (a mixed box) their interior term from 4x4 samples.

The boundary term asks what the camera sees on either side of a curve through a
``boundary.radiance.SideRadiance``: the direct renderer's shading (``DirectRadiance``), or
the path integrator's path-traced estimate (``render.path.boundary.primary.PathRadiance``, which
reuses the term for primary visibility through that interface).
"""
