"""Steps 2 and 3, the continuous part, on the tape: what the hits look like.

* ``surface``: the surface interaction both integrators use (``surface_at``): a hit's point,
  normals and UV recomputed from its primitive and ray, or a point placed on a primitive;
* ``lighting``: materials (textures, Lambert + Blinn-Phong) lit by the scene's lights, each
  light giving its own direction and irradiance (``Light.incidence``);
* ``hits``: the one function that shades hits, camera hits or mirror hits;
  ``mirrors``: the reflected rays of mirror materials;
* ``compiled``: ``surface`` and ``lighting``'s functions for a mesh's camera hits, compiled
  by ``minidiff.compile`` (one node on the tape); ``fused``: the image off the tape where
  nothing is differentiated.
"""
