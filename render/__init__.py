"""render: a differentiable ray tracer built on minidiff.

The folders are the pipeline, in order (``docs/architecture.md``): ``scene/`` (what a
scene is: objects, materials, lights, the camera model, mesh and image files, the teapot,
the cache of results computed from a scene's values), ``trace/`` (step 1, plain arrays:
which primitive each ray hits, which lights each hit sees), ``shade/`` (steps 2-3, on the
tape: surfaces recomputed from the hits, lights and materials, mirror bounces),
``edges/`` (step 4: silhouettes and shadow edges blended on the tape), ``film.py`` (step
5: pixels from samples); ``renderer.py`` calls them top to bottom. ``inverse/`` uses the
renderer: optimisation, gradient images (forward mode), the paper's experiments, and the
plots and JSON they write. Command lines belong to the scripts
(``examples/script_support.py``).
"""

from render.inverse.gradient_image import gradient_image
from render.inverse.optimize import FlatParameters, History, OptimizationError, image_loss, optimize
from render.renderer import RenderInfo, render
from render.scene.image import load_image, mse, psnr, save_image, write_gradient_png
from render.scene.meshio import load_mesh
from render.scene.scene import (
    Camera,
    DirectionalLight,
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
    "Accelerator", "Camera", "DirectionalLight", "Material", "Mesh", "PointLight", "Scene",
    "Sphere", "Transform", "RenderInfo", "render", "load_image", "save_image", "mse", "psnr",
    "load_mesh",
    "paper_scene", "teapot", "teapot_geometry", "optimize", "FlatParameters", "History",
    "OptimizationError", "image_loss", "gradient_image", "write_gradient_png",
]  # fmt: skip
