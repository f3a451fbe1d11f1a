"""render: a differentiable ray tracer built on minidiff.

Read in this order: ``renderer.py`` (the pipeline on one screen), then each step's module:
``scene.py`` (what a scene is), ``teapot.py`` (the reference scene), ``camera.py`` (rays),
``visibility.py`` (which primitive each ray hits, which lights each hit sees; built on
``bvh.py`` / ``intersect.py`` / ``accel.py``), ``geometry.py`` (hits recomputed on the
tape), ``shading.py`` (lights and materials), ``cache.py`` (reuse between renders),
``edges.py`` / ``topology.py`` / ``shadow_edges.py`` (the motion of silhouettes and shadow
edges, ``antialias=True``), ``reflection.py`` (mirror rays), ``raster.py`` (camera-ray
hits by rasterisation, shadow rays seen from the light), ``gradient_image.py`` (forward
mode: where in the picture a parameter acts), ``image.py`` / ``meshio.py`` / ``jsonio.py``
(files), ``optimize.py`` (inverse rendering), ``experiments.py`` (the paper's experiments,
as functions returning numbers and images) and ``plot.py`` (a dependency-free line plot
for loss curves).
Command lines and output writing belong to the scripts: ``examples/script_support.py``.
"""

from render.inverse.gradient_image import gradient_image
from render.inverse.optimize import FlatParameters, History, OptimizationError, image_loss, optimize
from render.renderer import RenderInfo, render
from render.scene.image import load_image, mse, psnr, save_image, write_gradient_png
from render.scene.meshio import load_mesh
from render.scene.scene import Camera, DirectionalLight, Material, Mesh, PointLight, Scene, Sphere
from render.scene.teapot import paper_scene, teapot, teapot_geometry
from render.trace.accel import Accelerator

__all__ = [
    "Accelerator", "Camera", "DirectionalLight", "Material", "Mesh", "PointLight", "Scene",
    "Sphere", "RenderInfo", "render", "load_image", "save_image", "mse", "psnr", "load_mesh",
    "paper_scene", "teapot", "teapot_geometry", "optimize", "FlatParameters", "History",
    "OptimizationError", "image_loss", "gradient_image", "write_gradient_png",
]  # fmt: skip
