"""The compiled path tracer (``render.path.twin.kernel``) against the readable reference: the
NumPy sampler (``render.path.sample.tracer.PathSampler``) for every decision of every path, and the
radiance on the tape (``render.path.gradient.transport.path_radiance``) for what each path carries.

The kernel must make the same decisions from the same random numbers (integers and flags
exactly, coordinates and weights to rounding) and compute the same radiance up to the order
of floating-point operations; its image must not depend on the number of threads, nor its
records on which other paths are in the batch.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.path import render_path
from render.path.gradient.transport import path_radiance
from render.path.sample.records import PathBatch
from render.path.sample.tracer import CAMERA, MIRROR, PathSampler
from render.path.twin import kernel
from render.scene.camera import camera_frame
from render.scene.cornell import box_mesh, cornell_box
from render.scene.placement import placed
from tests.render.path.test_replay import every_kind

#: |kernel's radiance - tape's| <= RTOL * max |tape's|, per path and per pixel. Measured
#: worst ratio (this machine, the kernel of commit e2ef0a2): 1.0e-15 on every_kind (its
#: image 1.0e-15), 2e-16 on the Cornell box; 1.4e-13 over 400 drawn scenes, at camera rays
#: that meet a sphere: the kernel shades the point its BVH found, the tape the point it
#: recomputes from the ray (they differ by ~1e-13 of their size).
RTOL = 1e-12
#: Fields of ``Vertices`` that are decisions (integers, flags): equal exactly.
EXACT_FIELDS = ("rows", "prim", "form", "nee_prim", "next", "escape", "lit")
#: Fields that are coordinates, weights or densities: equal to RTOL of their scale.
FLOAT_FIELDS = ("local", "emit_weight", "nee_weight", "next_pdf", "survive", "escape_dir")


# --------------------------------------------------------------------------------------
# Shared: samplers, the reference, the comparisons
# --------------------------------------------------------------------------------------


def sampler_of(
    scene: render.Scene, spp: int, max_depth: int, rr_depth: int, seed: int
) -> PathSampler:
    """The ``PathSampler`` of ``scene`` placed in world space."""
    with md.no_grad():
        world = placed(scene)
    return PathSampler(world, spp, max_depth, rr_depth, seed)


def all_paths(sampler: PathSampler) -> np.ndarray:
    """(H * W * spp,) every path id of the image, in order."""
    camera = sampler.scene.camera
    return np.arange(camera.width * camera.height * sampler.spp, dtype=np.int64)


def reference_radiance(sampler: PathSampler, batch: PathBatch) -> np.ndarray:
    """(N, 3) each path's radiance as the tape computes it (``path_radiance``)."""
    world = sampler.scene
    with md.no_grad():
        return path_radiance(world, camera_frame(world.camera), sampler, batch).data


def reference_image(sampler: PathSampler) -> np.ndarray:
    """(H, W, 3) the mean of every pixel's spp reference radiances, summed in sample order
    (as ``render_path``'s tape does)."""
    camera = sampler.scene.camera
    radiance = reference_radiance(sampler, sampler.sample(all_paths(sampler)))
    samples = radiance.reshape(camera.height, camera.width, sampler.spp, 3)
    total = samples[:, :, 0]
    for s in range(1, sampler.spp):
        total = total + samples[:, :, s]
    return total * (1.0 / sampler.spp)


def worst_ratio(values: np.ndarray, reference: np.ndarray) -> float:
    """max |values - reference| / max |reference| (reference not all zero)."""
    scale = np.abs(reference).max()
    assert scale > 0, "a comparison with zeros only would test nothing"
    return float(np.abs(values - reference).max() / scale)


def assert_same_decisions(batch: PathBatch, reference: PathBatch) -> None:
    """Every field of both batches equal: decisions exactly, floats to RTOL of their
    scale. ``nee_local`` is compared where NEE found its point visible (``nee_prim`` >= 0):
    the sampler also keeps the point of a hidden one, the kernel does not, and the tape reads
    it only where ``nee_weight`` > 0."""
    np.testing.assert_array_equal(batch.paths, reference.paths)
    np.testing.assert_array_equal(batch.missed, reference.missed)
    _assert_close(batch.coords, reference.coords, "coords")
    assert len(batch.vertices) == len(reference.vertices), "number of depths"
    for depth, (ours, theirs) in enumerate(zip(batch.vertices, reference.vertices, strict=True)):
        for name in EXACT_FIELDS:
            a, b = getattr(ours, name), getattr(theirs, name)
            assert a.dtype == b.dtype, f"depth {depth}: {name} {a.dtype} != {b.dtype}"
            np.testing.assert_array_equal(a, b, err_msg=f"depth {depth}: {name}")
        for name in FLOAT_FIELDS:
            _assert_close(getattr(ours, name), getattr(theirs, name), f"depth {depth}: {name}")
        seen = theirs.nee_prim >= 0
        _assert_close(ours.nee_local[seen], theirs.nee_local[seen], f"depth {depth}: nee_local")


def _assert_close(values: np.ndarray, reference: np.ndarray, what: str) -> None:
    assert values.shape == reference.shape, f"{what}: shape {values.shape} != {reference.shape}"
    scale = max(np.abs(reference).max(initial=0.0), 1e-300)
    np.testing.assert_allclose(values, reference, rtol=0, atol=RTOL * scale, err_msg=what)


def check_against_reference(sampler: PathSampler) -> tuple[PathBatch, float]:
    """The kernel's batch of every path against the sampler's (decisions), its radiance
    against the tape's and its image against the reference image (to RTOL); the reference
    batch and the worst ratio of the radiances."""
    paths = all_paths(sampler)
    batch, radiance = kernel.sample_paths(sampler, paths)
    reference = sampler.sample(paths)
    assert_same_decisions(batch, reference)
    ratio = worst_ratio(radiance, reference_radiance(sampler, reference))
    assert ratio <= RTOL, f"radiance differs by {ratio:.3g} of its scale"
    image_ratio = worst_ratio(kernel.render_image(sampler), reference_image(sampler))
    assert image_ratio <= RTOL, f"image differs by {image_ratio:.3g} of its scale"
    return reference, ratio


# --------------------------------------------------------------------------------------
# 1-2: decisions and radiance on fixed scenes
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, spp, max_depth, rr_depth, seed",
    [
        (lambda: cornell_box(8, 8), 3, 5, 5, 7),
        (every_kind, 3, 4, 5, 1),
        (every_kind, 2, 8, 2, 3),  # deep paths that Russian roulette ends
    ],
    ids=["cornell", "every_kind", "every_kind_roulette"],
)
def test_the_kernel_makes_the_samplers_decisions_and_the_tapes_radiance(
    make, spp, max_depth, rr_depth, seed
):
    sampler = sampler_of(make(), spp, max_depth, rr_depth, seed)
    reference, _ = check_against_reference(sampler)
    vertices = reference.vertices
    assert any(v.nee_prim.max(initial=-1) >= 0 for v in vertices)  # NEE found the light
    if any(obj.material.reflective for obj in sampler.objects):  # mirror bounces were made
        assert any((v.form == MIRROR).any() for v in vertices)
    if sampler.scene.background.data.any():  # paths left through the open front
        assert any(v.escape.any() for v in vertices)
    if rr_depth < max_depth:  # Russian roulette played
        assert any((v.survive < 1).any() for v in vertices)


# --------------------------------------------------------------------------------------
# 3: drawn scenes
# --------------------------------------------------------------------------------------


def _material(draw, rng: np.random.Generator, emission: float = 0.0) -> render.Material:
    """A drawn material: a diffuse albedo, sometimes a glossy lobe, sometimes a mirror."""
    glossy, mirror = draw(st.booleans()), draw(st.booleans())
    return render.Material(
        rng.uniform(0.0, 0.9, 3), specular=rng.uniform(0.05, 0.5) if glossy else 0.0,
        shininess=rng.uniform(1.0, 60.0), reflectance=rng.uniform(0.1, 0.6) if mirror else 0.0,
        emission=emission,
    )  # fmt: skip


def _facing_triangle(eye, look_at, fov: float, emission) -> render.Mesh:
    """An emissive triangle a third of the way from ``eye`` to ``look_at``, across the
    middle of the view, its front (the emitting side) towards the eye."""
    forward = (look_at - eye) / np.linalg.norm(look_at - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    centre = eye + (look_at - eye) / 3.0
    size = 0.35 * math.tan(math.radians(fov) / 2) * np.linalg.norm(centre - eye)
    corners = centre + size * np.array([-right - up, right - up, up])  # normal -forward
    return render.Mesh(
        corners, np.array([[0, 1, 2]]), render.Material((0.3,) * 3, emission=emission)
    )


def drawn_view(draw, rng) -> tuple[render.Camera, render.Mesh]:
    """A drawn camera (8x8 to 12x12 pixels, 2.5 to 4 from the origin, looking near it) and
    an emissive triangle in the middle of its view, facing it (``_facing_triangle``)."""
    azimuth, elevation = rng.uniform(0, 2 * math.pi), rng.uniform(-1.0, 1.0)
    eye = rng.uniform(2.5, 4.0) * np.array(
        [math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
         math.cos(elevation) * math.cos(azimuth)]
    )  # fmt: skip
    look_at, fov = rng.uniform(-0.2, 0.2, 3), rng.uniform(30.0, 60.0)
    triangle = _facing_triangle(eye, look_at, fov, rng.uniform(0.5, 3.0, 3))
    width, height = draw(st.integers(8, 12)), draw(st.integers(8, 12))
    return render.Camera(eye, look_at, (0.0, 1.0, 0.0), fov, width, height), triangle


@st.composite
def small_scenes(draw) -> render.Scene:
    """A few boxes and spheres of drawn materials near the origin, an emissive sphere (an
    area light), a mirror sphere, an emissive triangle seen directly; sometimes a point
    light, a directional light, a background; a drawn camera 8x8 to 12x12 pixels."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    objects = []
    for _ in range(draw(st.integers(0, 2))):
        objects.append(
            box_mesh(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35, 3), _material(draw, rng))
        )
    for _ in range(draw(st.integers(0, 2))):
        objects.append(
            render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35), _material(draw, rng))
        )
    emitter = render.Material(rng.uniform(0.0, 0.5, 3), emission=rng.uniform(0.5, 5.0, 3))
    objects.append(render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.3), emitter))
    mirror = render.Material(rng.uniform(0.0, 0.3, 3), reflectance=rng.uniform(0.3, 0.7))
    objects.append(render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35), mirror))
    lights = []
    if draw(st.booleans()):
        lights.append(render.PointLight(rng.uniform(-1.5, 1.5, 3), rng.uniform(0.5, 3.0)))
    if draw(st.booleans()):
        lights.append(render.DirectionalLight(rng.normal(size=3), rng.uniform(0.2, 1.0)))
    background = rng.uniform(0.0, 1.0, 3) if draw(st.booleans()) else (0.0, 0.0, 0.0)
    camera, triangle = drawn_view(draw, rng)
    return render.Scene([*objects, triangle], lights, camera, background=background)


@settings(max_examples=8)
@given(
    scene=small_scenes(),
    spp=st.integers(1, 3),
    max_depth=st.integers(1, 6),
    rr_depth=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
)
def test_drawn_scenes_give_the_samplers_decisions_and_the_tapes_radiance(
    scene, spp, max_depth, rr_depth, seed
):
    sampler = sampler_of(scene, spp, max_depth, rr_depth, seed)
    reference, _ = check_against_reference(sampler)
    # The emissive triangle (the last primitive's object, the last triangle) is seen.
    first = reference.vertices[0]
    triangle = sampler.n_triangles - 1
    assert np.any((first.prim == triangle) & (first.form == CAMERA))


# --------------------------------------------------------------------------------------
# 4: threads
# --------------------------------------------------------------------------------------

#: Renders on 1 and 2 threads in one process: 12 x 12 pixels (144, three of the kernel's
#: blocks of 64: two jobs share them) and 288 paths (five blocks).
_THREADS = """
import numba, numpy as np
from render.path.twin import kernel
from render.path.sample.tracer import PathSampler
from render.scene.cornell import cornell_box
from render.scene.placement import placed
sampler = PathSampler(placed(cornell_box(12, 12)), 2, 5, 2, 4)
paths = np.arange(12 * 12 * 2, dtype=np.int64)[::-1].copy()
runs = []
for n in (1, 2):
    numba.set_num_threads(n)
    assert numba.get_num_threads() == n
    runs.append((kernel.render_image(sampler), kernel.sample_paths(sampler, paths)[1]))
(image_1, radiance_1), (image_2, radiance_2) = runs
assert np.abs(image_1).max() > 0
assert np.array_equal(image_1, image_2), "image"
assert np.array_equal(radiance_1, radiance_2), "radiance"
print("same bits")
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    """In a new process (a pytest-xdist worker is limited to one Numba thread)."""
    env = {**os.environ, "NUMBA_NUM_THREADS": "2"}
    done = subprocess.run(
        [sys.executable, "-c", _THREADS], env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "same bits"


# --------------------------------------------------------------------------------------
# 5: batches
# --------------------------------------------------------------------------------------


def _per_path(batch: PathBatch) -> dict[tuple[int, str], dict[int, object]]:
    """Every record of the batch by (depth, field), then by path id: the row's value."""
    records = {}
    for depth, vertices in enumerate(batch.vertices):
        ids = batch.paths[vertices.rows]
        for name in EXACT_FIELDS[1:] + FLOAT_FIELDS + ("nee_local",):
            values = getattr(vertices, name)
            values = values.T if name == "lit" else values
            records[depth, name] = {int(p): values[i] for i, p in enumerate(ids)}
    return records


def test_a_subset_of_paths_gets_the_same_records_and_radiance_bit_for_bit():
    sampler = sampler_of(every_kind(), 3, 6, 2, 5)
    paths = all_paths(sampler)
    full, radiance = kernel.sample_paths(sampler, paths)
    some = np.random.default_rng(0).choice(paths, 50, replace=False)  # shuffled
    part, part_radiance = kernel.sample_paths(sampler, some)
    np.testing.assert_array_equal(part_radiance, radiance[some])
    np.testing.assert_array_equal(part.coords, full.coords[some])
    np.testing.assert_array_equal(part.missed, full.missed[some])
    everything, subset = _per_path(full), _per_path(part)
    assert subset and len(subset) <= len(everything)
    for key, values in subset.items():
        assert len(values) > 0
        for path, value in values.items():
            np.testing.assert_array_equal(value, everything[key][path], err_msg=f"{key} {path}")
    # Each path has records at as many depths in the subset as in the full batch.
    for depth in range(len(full.vertices)):
        reached = set(everything[depth, "prim"]) & set(some.tolist())
        assert reached == set(subset.get((depth, "prim"), {})), f"depth {depth}"


# --------------------------------------------------------------------------------------
# 6: which scenes the kernel takes
# --------------------------------------------------------------------------------------


class UncompiledPointLight(render.PointLight):
    """A point light that the compiled kernels do not shade (the tape does)."""

    compiled_shading = False


def test_the_kernel_applies_to_float64_scenes_with_compiled_lights():
    assert kernel.applies(placed(cornell_box(4, 4)))
    assert kernel.applies(placed(every_kind(4)))


def test_a_float32_scene_is_left_to_the_reference():
    scene = cornell_box(6, 6)
    scene.objects[0].material.albedo = md.tensor(np.float32([0.7, 0.6, 0.5]))
    scene.validate()
    sampler = sampler_of(scene, 2, 3, 5, 0)
    assert not kernel.applies(sampler.scene)
    with md.no_grad():
        image = render_path(scene, spp=2, max_depth=3, seed=0)
    assert worst_ratio(image.data, reference_image(sampler)) <= RTOL


def test_a_light_without_compiled_shading_is_left_to_the_reference():
    """The reference renders it, and its image is the kernel's for the same light
    shaded by the kernel."""
    scene = cornell_box(6, 6)
    scene.lights = [UncompiledPointLight((0.2, 0.5, 0.3), 1.5)]
    assert not kernel.applies(placed(scene))
    with md.no_grad():
        image = render_path(scene, spp=2, max_depth=3, seed=2).data
    scene.lights = [render.PointLight((0.2, 0.5, 0.3), 1.5)]
    compiled = kernel.render_image(sampler_of(scene, 2, 3, 5, 2))
    assert worst_ratio(image, compiled) <= RTOL
