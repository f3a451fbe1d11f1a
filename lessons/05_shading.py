# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 5 — Shading: Lambert, Blinn-Phong, shadows
#
# Once visibility has said which surface a camera ray hits, shading says what colour the
# pixel gets: the radiance `L` that leaves the hit point towards the eye. The renderer does
# direct illumination only (`render/shade/lighting.py`, called from `render/renderer.py`): for
# each light it adds
#
#     L = f · E · max(0, n·l)       with   E = I / r²   (point light of intensity I at
#                                                       distance r; a directional light
#                                                       gives its irradiance E directly)
#
# times the light's colour, where `n` is the unit normal facing the viewer, `l` the unit
# direction to the light, and the BRDF `f` is
#
# * **Lambert** (diffuse): `f_d = albedo / π`. The `1/π` makes a white surface reflect
#   exactly the power it receives: `∫ (1/π) cos θ dω = 1` over the hemisphere.
# * **Blinn-Phong** (glossy), optional: `f_s = k_s · (m + 8)/(8π) · max(0, n·h)^m`, with the
#   half vector `h = normalize(l + v)` (`v` towards the eye), shininess `m` and the
#   approximate energy normalisation `(m + 8)/(8π)`.
#
# plus a constant `ambient` radiance added where the material is seen. **Shadows** multiply
# each light's term by 0 or 1: a shadow ray from the hit point towards the light either
# reaches it or is blocked (`render/trace/visibility.py`: for a point light answered from
# the light's side, rasterising the scene as seen from the light
# (`render/trace/light_view.py`); for directional lights and rays the light's view cannot
# take, on the BVH of lesson 4; both give the same answers). Like the choice of primitive,
# that answer is a constant on the tape.
#
# We check the formulas on a case with a closed form, then render a small scene.
# (`tests/render/shade/test_closed_form.py` holds the renderer to closed forms the same way, for
# triangles, spheres, textures, directional lights and shadows.)

# %%
import math

import numpy as np
from course import figures_folder, save_and_show

import render
from render.inverse.plot import line_figure
from render.scene.camera import primary_rays
from render.scene.teapot import PAPER_ALBEDO

# This lesson's figures go to out/lessons/05_shading/ (or under $LESSONS_OUT).
OUT = figures_folder("05_shading")

# %% [markdown]
# ## A plane under a point light
#
# The plane `y = 0`, a point light at height `h` straight above the origin, a camera
# looking straight down. At the point `p` at distance `ρ` from the origin,
# `r² = h² + ρ²` and `cos θ = h / r`, so the Lambertian radiance is
#
#     L(ρ) = (albedo/π) · I · h / r³ = (albedo/π) · (I/h²) · (1 + ρ²/h²)^(−3/2):
#
# the inverse square law and the cosine together give the `cos³ θ` fall-off. The camera
# has an odd number of pixels, so its centre pixel looks at the origin itself, where
# `L(0) = (albedo/π) · I/h²`.

# %%
ALBEDO, INTENSITY, LIGHT_HEIGHT, N = 0.6, 10.0, 2.0, 33
camera = render.Camera(position=(0, 3, 0), look_at=(0, 0, 0), up=(0, 0, -1), fov=60.0,
                       width=N, height=N)  # fmt: skip
s = 4.0
plane_vertices = [(-s, 0, s), (s, 0, s), (s, 0, -s), (-s, 0, -s)]


def plane_scene(material, lights):
    return render.Scene([render.Mesh(plane_vertices, [[0, 1, 2], [0, 2, 3]], material)], lights,
                        camera)  # fmt: skip


light = render.PointLight((0, LIGHT_HEIGHT, 0), INTENSITY)
lambert = render.render(plane_scene(render.Material((ALBEDO,) * 3), [light])).data
centre_rendered = float(lambert[N // 2, N // 2, 0])
centre_formula = ALBEDO / math.pi * INTENSITY / LIGHT_HEIGHT**2
print(f"centre pixel: rendered {centre_rendered:.10f}, formula {centre_formula:.10f}")

# Every pixel: where its ray meets y = 0 (rays from lesson 3), then the formula.
eye, directions = primary_rays(camera)
points = eye + (-eye[1] / directions[:, 1])[:, None] * directions  # (N*N, 3) on y = 0
rho = np.hypot(points[:, 0], points[:, 2])
r = np.hypot(rho, LIGHT_HEIGHT)
lambert_formula = (ALBEDO / math.pi * INTENSITY * LIGHT_HEIGHT / r**3).reshape(N, N)
lambert_error = float(np.abs(lambert[..., 0] / lambert_formula - 1).max())
corner_to_centre = float(lambert[0, 0, 0] / centre_rendered)
print(f"largest relative difference over all {N * N} pixels: {lambert_error:.1e}")
print(f"corner / centre: {corner_to_centre:.4f}")

# %% [markdown]
# The centre pixel is `0.4774648293` <!-- check: centre_rendered --> `= 0.6/π · 10/2²`,
# and every pixel matches `L(ρ)` to a relative `1e-14` <!-- check: lambert_error < -->.
# The corner pixel sees the plane at `ρ ≈ 2.4`, where the light is only
# `0.2672` <!-- check: corner_to_centre --> of the centre's. `falloff.png` plots the
# middle row against the formula.

# %%
middle = N // 2
x_row = points.reshape(N, N, 3)[middle, :, 0]
figure = line_figure(
    {
        "rendered (middle row)": (x_row, lambert[middle, :, 0]),
        "(albedo/pi) I h / r^3": (np.linspace(x_row[0], x_row[-1], 200),
            ALBEDO / math.pi * INTENSITY * LIGHT_HEIGHT
            / np.hypot(np.linspace(x_row[0], x_row[-1], 200), LIGHT_HEIGHT) ** 3),
    },
    title="A plane under a point light: the cos^3 fall-off",
    xlabel="x on the plane",
    ylabel="radiance",
)  # fmt: skip
save_and_show(figure, OUT / "falloff.png")

# %% [markdown]
# ## Adding a Blinn-Phong lobe
#
# With `specular = k_s` the material adds `f_s` to the BRDF. At the centre pixel the eye,
# the light and the normal are all straight up, so `l = v = h = n`, `n·h = 1` and
# `f_s = k_s (m + 8)/(8π)` whatever the shininess does elsewhere. Away from the centre,
# `n·h < 1` and the lobe dies off as `(n·h)^m`: a highlight.

# %%
KS, SHININESS = 0.5, 20.0
glossy_material = render.Material((ALBEDO,) * 3, specular=KS, shininess=SHININESS)
glossy = render.render(plane_scene(glossy_material, [light])).data
to_light = np.array([0, LIGHT_HEIGHT, 0]) - points
to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
to_eye = eye - points
to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
half = (to_light + to_eye) / np.linalg.norm(to_light + to_eye, axis=1, keepdims=True)
f_s = KS * (SHININESS + 8) / (8 * math.pi) * np.maximum(half[:, 1], 0) ** SHININESS
glossy_formula = ((ALBEDO / math.pi + f_s) * INTENSITY * to_light[:, 1] / r**2).reshape(N, N)
glossy_error = float(np.abs(glossy[..., 0] / glossy_formula - 1).max())
glossy_centre = float(glossy[middle, middle, 0])
specular_share = 1 - centre_rendered / glossy_centre
print(f"glossy centre {glossy_centre:.6f}; specular share {specular_share:.3f}; "
      f"largest relative difference to the formula {glossy_error:.1e}")  # fmt: skip

# %% [markdown]
# The centre pixel becomes (0.6/π + 0.5·28/(8π)) · 10/4 = `1.870`
# <!-- check: glossy_centre -->, a share of `0.745` <!-- check: specular_share --> of it
# specular, and the
# whole image matches the formula (with `h` computed per pixel) to a relative `1e-14`
# <!-- check: glossy_error < -->.
#
# ## Shadows
#
# Now a small square at height 1 between the plane and a light moved off-axis. A point
# `p` on the plane is in shadow exactly when the segment from `p` to the light passes
# through the square: it crosses the square's plane `y = 1` at `p + (1/y_L)·(light − p)`.
# The renderer's shadow rays (on the BVH) must agree with that test at every plane pixel.

# %%
light_position = np.array([0.5, 2.5, 0.3])
centre_sq, half_sq = np.array([-0.2, 1.0, 0.0]), 0.25
square = [centre_sq + (dx, 0, dz) for dx, dz in ((-half_sq, half_sq), (half_sq, half_sq),
          (half_sq, -half_sq), (-half_sq, -half_sq))]  # fmt: skip
occluder = render.Mesh(square, [[0, 1, 2], [0, 2, 3]], render.Material((0.9, 0.9, 0.9)))
shadow_scene = plane_scene(render.Material((ALBEDO,) * 3), [render.PointLight(light_position, 10)])
shadow_scene.objects.append(occluder)
shadowed, info = render.render(shadow_scene, return_info=True)
on_plane = (info.prim_id[..., 0] >= 0) & (info.prim_id[..., 0] < 2)  # triangles 0, 1
crossing = points + (1.0 / light_position[1]) * (light_position - points)
inside = (np.abs(crossing[:, 0] - centre_sq[0]) < half_sq) & (
    np.abs(crossing[:, 2] - centre_sq[2]) < half_sq
)
predicted_dark = inside.reshape(N, N)
rendered_dark = ~info.lit[0, ..., 0]
shadow_pixels = int((rendered_dark & on_plane).sum())
shadow_mismatches = int((rendered_dark != predicted_dark)[on_plane].sum())
dark_values_zero = bool((shadowed.data[rendered_dark & on_plane] == 0).all())
print(f"{on_plane.sum()} plane pixels, {shadow_pixels} in shadow, "
      f"{shadow_mismatches} disagree with the segment test; shadowed pixels black: "
      f"{dark_values_zero}")  # fmt: skip

# %% [markdown]
# Of the plane's visible pixels, `40` <!-- check: shadow_pixels --> are in shadow, and
# `0` <!-- check: shadow_mismatches --> disagree with the segment test. With a single
# light and no ambient term, a shadowed pixel is exactly black.
#
# ## A small scene
#
# The paper's teapot standing on a grey ground (`render.paper_scene(ground=True)`),
# 128 × 128, rendered three ways and saved side by side in `teapot_shading.png` (sRGB for
# the screen): Lambert without shadows, Lambert with shadows, and a glossy teapot
# (`specular = 0.3`, `shininess = 40`, a little ambient) with shadows. Without shadows the
# ground behind the teapot is lit as if the teapot were not there. (The facets are the
# paper's flat shading: one normal per triangle.)

# %%
scene = render.paper_scene(width=128, height=128, ground=True)
no_shadows = render.render(scene, shadows=False).data
with_shadows = render.render(scene).data
scene.objects[0].material = render.Material(PAPER_ALBEDO, specular=0.3,
                                            shininess=40.0, ambient=0.01)  # fmt: skip
glossy_teapot, teapot_info = render.render(scene, return_info=True)
strip = np.concatenate([no_shadows, with_shadows, glossy_teapot.data], axis=1)
strip = np.repeat(np.repeat(strip, 2, axis=0), 2, axis=1)  # twice the size, for the screen
render.save_image(strip, OUT / "teapot_shading.png", srgb=True)
ground_hits = teapot_info.prim_id[..., 0] >= render.teapot().num_faces
teapot_shadow_share = float((~teapot_info.lit[0, ..., 0])[ground_hits].mean())
print(f"share of the visible ground in the teapot's shadow: {teapot_shadow_share:.3f}")

# %% [markdown]
# In this view `0.049` <!-- check: teapot_shadow_share --> of the visible ground lies in the
# teapot's shadow.
#
# ## Mirror reflection
#
# A material with `reflectance = ρ` adds, at each hit, `ρ` times the radiance arriving
# along the mirror direction (`render/shade/mirrors.py`). For a camera ray of unit direction
# `d` hitting a surface of unit normal `n`, the mirror ray leaves the hit point along
#
#     r = d − 2 (d·n) n ,
#
# the component of `d` along `n` reversed and the rest kept. It is traced like a camera
# ray (which primitive it hits: a constant, in `RenderInfo.bounces`), shaded like one
# (lights and shadows at the point it hits, `RenderInfo.bounce_lit`), and may reflect
# again, up to `render(..., max_bounces=)` times (2 by default; 0 turns reflection off).
#
# An ideal mirror floor, `Material((0, 0, 0), reflectance=1)` (no colour of its own), under
# the teapot has a closed-form check: what a mirror pixel shows is exactly what a camera
# mirrored through the floor's plane `y = −0.5` sees of the scene without the floor, in the
# same row, with left and right swapped (a reflection reverses handedness).
# (`tests/render/shade/test_reflection.py` checks this on random scenes.)

# %%
M = 96
mirror_floor = render.Material((0.0, 0.0, 0.0), reflectance=1.0)
mirror_scene = render.paper_scene(width=M, height=M, ground=True, ground_material=mirror_floor)
mirrored_image, mirror_info = render.render(mirror_scene, return_info=True)
flip = np.array([1.0, -1.0, 1.0])
eye = mirror_scene.camera


def through_floor(p):  # the reflection of a point through the plane y = -0.5
    return p * flip + np.array([0.0, -1.0, 0.0])


mirrored_camera = render.Camera(
    through_floor(eye.position.data),
    through_floor(eye.look_at.data),
    up=eye.up.data * flip,
    fov=eye.fov.data,
    width=M,
    height=M,
)
teapot_only = render.Scene([mirror_scene.objects[0]], mirror_scene.lights, mirrored_camera)
seen, seen_info = render.render(teapot_only, return_info=True)
seen_image, seen_ids = seen.data[:, ::-1], seen_info.prim_id[:, ::-1, 0]  # columns swapped
on_mirror = mirror_info.prim_id[..., 0] >= render.teapot().num_faces
in_mirror = mirror_info.bounces[0][..., 0]  # what each pixel's mirror ray hit
same = on_mirror & (in_mirror == seen_ids)
same &= (mirror_info.bounce_lit[0][..., 0] == seen_info.lit[:, :, ::-1, 0]).all(axis=0)
mirror_pixels = int(on_mirror.sum())
mirror_mismatch = float(np.abs(mirrored_image.data[same] - seen_image[same]).max())
teapot_in_mirror = int((on_mirror & (in_mirror >= 0)).sum())
no_bounce = render.render(mirror_scene, max_bounces=0).data
print(
    f"{mirror_pixels} mirror pixels, {same.sum()} with the mirrored camera's decisions, "
    f"{teapot_in_mirror} showing the teapot; largest difference {mirror_mismatch:.1e}; "
    f"with max_bounces=0 the mirror is black: {bool((no_bounce[on_mirror] == 0).all())}"
)
render.save_image(np.repeat(np.repeat(mirrored_image.data, 2, 0), 2, 1),
                  OUT / "mirror_floor.png", srgb=True)  # fmt: skip
print(f"figures in {OUT}")

# %% [markdown]
# Of the `4,182` <!-- check: mirror_pixels --> pixels that see the mirror (96 × 96),
# every one makes the same decisions as the mirrored camera's pixel, `1,077`
# <!-- check: teapot_in_mirror --> of them show the teapot, and the colours agree to
# `1e-14` <!-- check: mirror_mismatch < --> (`mirror_floor.png`). With `max_bounces=0` the
# floor is black: it has no colour of its own.
#
# ## Exercises
#
# 1. Replace the point light by a `render.DirectionalLight` that travels at 60° from the
#    plane's normal with irradiance `E = 2`: show that every pixel of the plane is
#    `E · albedo/π · cos 60°`, a constant (no fall-off: the light is at infinity).
# 2. Move the point light to `(1, 2, 0)`. Where on the plane is the Lambertian radiance
#    largest — under the light, or where `cos θ` is largest? Find the brightest pixel of the
#    render, and explain with `L ∝ h / r³`.
# 3. How good is the normalisation `(m + 8)/(8π)`? For light and view both along the normal,
#    compute the reflected fraction `∫ f_s cos θ dω` over the hemisphere of view directions
#    (numerically, with `k_s = 1`) for `m = 1, 10, 100`.
# 4. **A Lambert shader on the tape** (you build it). Write
#    `my_lambert(points, normals, albedo, light_position, intensity)` with minidiff
#    operations (`md.sum`, `md.maximum`, `md.sqrt`, arithmetic on tensors): the radiance
#    `albedo/π · I · max(n·l, 0) / r²` of k points lit by a point light, `(k, 3)`. Run
#    `check_lambert(my_lambert)` from `lessons/exercise_checks.py`: it renders a plane
#    with the library, computes yours at the same points, and compares the values *and*
#    the gradients of a weighted sum with respect to the light's position, the albedo and
#    the intensity (`backward` through your code and through the renderer's).
#
# Solutions: `lessons/solutions/05_shading.py`.
