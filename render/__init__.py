"""render: a differentiable ray tracer built on minidiff.

``render(scene)`` (``renderer.py``) makes the pipeline's calls top to bottom; each step
lives in its own folder, and a folder imports only from the ones before it
(``docs/architecture.md``):

* ``scene/``: what a scene is (objects, materials, lights that know their own geometry,
  the camera model, transforms), mesh and image files, the teapot, the cache of results
  computed from a scene's values;
* ``trace/`` (step 1, plain arrays): which primitive each ray hits, which lights each hit
  sees;
* ``shade/`` (steps 2-3, on the tape): surfaces recomputed from the hits, lit by the
  lights through the materials, mirror bounces;
* ``edges/`` (step 4): what moving edges add to the gradient: pairs of samples blended
  across silhouettes, creases and shadow edges (``antialias=True``), or the boundary
  integral over every curve where the image jumps (``antialias="boundary"``);
* ``film.py`` (step 5): pixels from samples;
* ``path/``: the path integrator (``render(..., integrator="path")``), light that bounces,
  by Monte Carlo, with the same split of discrete and continuous;
* ``inverse/``: what uses the renderer: optimisation, gradient images, the paper's
  experiments, reconstruction, a neural field, the renderer as a function of arrays;
* ``torch.py``, ``jax.py``: the bridges to PyTorch and JAX (optional extras).

Command lines belong to the scripts (``examples/script_support.py``).
"""

import minidiff  # noqa: F401  (first: its import makes Numba's cache see edits in any module)
from render.inverse.gradient_image import gradient_image
from render.inverse.optimize import FlatParameters, History, OptimizationError, image_loss, optimize
from render.renderer import RenderInfo, render
from render.scene.image import load_image, mse, psnr, save_image, write_gradient_png
from render.scene.meshio import load_mesh
from render.scene.scene import (
    Camera,
    DirectionalLight,
    Light,
    Material,
    Mesh,
    PointLight,
    Scene,
    Sphere,
    Transform,
)
from render.scene.teapot import paper_scene, teapot, teapot_geometry
from render.trace.accel import Accelerator

__all__ = [
    "Accelerator", "Camera", "DirectionalLight", "Light", "Material", "Mesh", "PointLight", "Scene",
    "Sphere", "Transform", "RenderInfo", "render", "load_image", "save_image", "mse", "psnr",
    "load_mesh",
    "paper_scene", "teapot", "teapot_geometry", "optimize", "FlatParameters", "History",
    "OptimizationError", "image_loss", "gradient_image", "write_gradient_png",
]  # fmt: skip
