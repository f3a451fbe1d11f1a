"""After the renderer: what uses it.

* ``optimize``: inverse rendering (the paper's Algorithm 1) and a flat-vector view for
  SciPy; ``gradient_image``: d image / d parameter in forward mode;
* ``experiments`` (the paper's sections 5.6-5.8), ``reconstruction`` (pose, shape, joint
  reconstruction), ``bleeding`` (a hidden wall's colour through the path integrator),
  ``networks`` (a neural field trained through the renderer), with ``shape`` (Laplacian,
  Large Steps, surface distances) and ``basin`` (coarse-to-fine, search) as their tools;
* ``reference``: the supersampled truth edge gradients are checked against;
* ``function``: the renderer as a function of arrays with its VJP and JVP (what
  ``render.torch`` and ``render.jax`` wrap); ``parallel``: independent runs over any
  executor; ``plot`` and ``jsonio``: figures and JSON of the results.
"""
