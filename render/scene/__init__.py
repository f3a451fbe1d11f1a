"""Step 0, the description of a scene, and what is remembered about it.

* ``scene``: the ``Scene`` and its ``Camera``, with every scene class re-exported;
  ``fields``: what they share (continuous parameters as ``minidiff.Tensor`` s, checked
  before every render, the supported ranges); ``lights``: ``PointLight`` and
  ``DirectionalLight``, each answering what the renderer asks of a light (its direction
  and irradiance at a point, its shadow rays, its cache key, the plane an occluder's edge
  sweeps in it); ``materials``: ``Material``; ``shapes``: ``Mesh``, ``Sphere``,
  ``Transform``.
* ``camera``: the camera's rays and frame; ``placement``: objects put in world space by
  their transforms, on the tape.
* ``meshio``, ``image``, ``teapot``, ``cornell``: mesh and image files, the paper's
  teapot scene, the Cornell box.
* ``cache``: a render's stage results, reused while the values they came from are
  unchanged; ``substitute``: a scene with some parameters replaced.
"""
