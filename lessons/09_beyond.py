# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 9 — Beyond the scene's parameters: pose, shape, a neural field
#
# Until now the optimiser moved numbers that the scene holds: a light's position, an
# albedo, the camera. But a scene's tensors need not be leaves. A mesh's vertices can be
# *computed* on the tape from a handful of parameters (a rotation angle, a displacement per
# vertex), a texture from the weights of a small network, and `backward` carries the image
# loss through the renderer *and* through that computation, by the chain rule:
#
#     ∂L/∂φ = (∂L/∂vertices) · (∂vertices/∂φ) .
#
# `render.optimize` accepts, instead of a scene, a function that rebuilds the computed
# tensors from the parameters and returns the rendered image; it is called once per
# iteration, so every iteration gets a fresh tape. Three small examples, each at 48 × 48.

# %%
import math
import time

import numpy as np
from course import figures_folder, save_and_show

import minidiff as md
import render
from render.inverse.plot import line_figure

# This lesson's figures go to out/lessons/09_beyond/ (or under $LESSONS_OUT).
OUT = figures_folder("09_beyond")
S = 48
lesson_start = time.perf_counter()


def strip(*images, factor=4):
    """Images side by side, clipped to [0, 1] and enlarged for the screen."""
    row = np.concatenate([np.clip(im, 0, 1) for im in images], axis=1)
    return np.repeat(np.repeat(row, factor, 0), factor, 1)


# %% [markdown]
# ## (a) Pose: a rigid motion of the teapot
#
# The teapot's rest vertices `V₀ = (x, y, z)` are constants; its pose is an angle `θ`
# about the vertical axis and a translation `t`, both leaves that require a gradient:
#
#     x' = cos θ · x + sin θ · z + t_x,     y' = y + t_y,     z' = −sin θ · x + cos θ · z + t_z .
#
# Every iteration computes the vertices from `(θ, t)` with minidiff operations and assigns
# them to the mesh. A rigid motion moves the silhouette, so we render with
# `antialias=True` (lesson 8), the target too, so that both sides of the loss are the same
# kind of image. Target: `θ = 25°`, `t = (0.15, 0, −0.1)`; start: the rest pose.

# %%
scene = render.paper_scene(S, S)
teapot = scene.objects[0]
rest = teapot.vertices.data.copy()
X, Y, Z = rest[:, 0], rest[:, 1], rest[:, 2]


def posed(theta, t):
    c, s = md.cos(theta), md.sin(theta)
    return md.stack([c * X + s * Z + t[0], Y + t[1], -s * X + c * Z + t[2]], axis=1)


TRUE_THETA, TRUE_T = math.radians(25.0), np.array([0.15, 0.0, -0.1])
with md.no_grad():
    teapot.vertices = posed(md.tensor(TRUE_THETA), md.tensor(TRUE_T))
    pose_target = render.render(scene, antialias=True).data
theta = md.tensor(0.0, requires_grad=True)
t = md.tensor(np.zeros(3), requires_grad=True)


def posed_image():
    teapot.vertices = posed(theta, t)
    return render.render(scene, antialias=True)


pose_start = posed_image().data
_, pose_history = render.optimize(posed_image, [theta, t], pose_target, lr=0.02, max_iters=200,
                                  quiet=True)  # fmt: skip
pose_final = posed_image().data
angle_error = abs(math.degrees(theta.item() - TRUE_THETA))
translation_error = float(np.linalg.norm(t.data - TRUE_T))
print(f"pose: theta {math.degrees(theta.item()):.3f} deg (true 25), t {t.data.round(4)}; "
      f"errors {angle_error:.3f} deg, {translation_error:.4f}; loss "
      f"{pose_history.loss[0]:.2e} -> {pose_history.loss[-1]:.2e}")  # fmt: skip
render.save_image(strip(pose_target, pose_start, pose_final), OUT / "pose.png", srgb=True)

# %% [markdown]
# In 200 steps the angle is found to within `1` <!-- check: angle_error < --> degree and
# the translation to within `0.02` <!-- check: translation_error < --> (`pose.png`: target,
# start, result). It stops short of exact: the loss levels off near `1e-4`. At 48 × 48 a
# small turn about the vertical axis and a small sideways shift change the picture in
# similar ways, so the loss is flat along that combination, and the edge term is an
# approximation at corners (lesson 8); we have not measured how much of the remaining
# error each causes.
#
# ## (b) Shape: moving vertices to match a silhouette
#
# A flat fan of 8 triangles around a centre, seen head-on and lit evenly: only its outline
# is visible, as in lesson 8's square. Its 8 rim vertices start on a circle of radius 0.5;
# the target is an ellipse with semi-axes 0.75 and 0.45, one vertex pushed out further. The
# parameters are the rim's 2-D displacements `δ` (16 numbers). Shape fitting usually adds
# a regulariser, here a discrete Laplacian that keeps each rim vertex near the midpoint of
# its neighbours:
#
#     L(δ) = L_image + λ Σᵢ ‖pᵢ − (pᵢ₋₁ + pᵢ₊₁)/2‖²,      p = p₀ + δ .
#
# We fit with `λ = 1e-3` and without (`λ = 0`), and then ask when the regulariser earns
# its place.

# %%
K = 8
angles = np.arange(K) * 2 * np.pi / K


def rim(rx, ry):
    return np.stack([rx * np.cos(angles), ry * np.sin(angles)], axis=1)


fan_faces = [[0, 1 + i, 1 + (i + 1) % K] for i in range(K)]
flat_camera = render.Camera(position=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov=40.0,
                            width=S, height=S)  # fmt: skip
start_rim = rim(0.5, 0.5)
true_rim = rim(0.75, 0.45)
true_rim[1] *= 1.2  # one corner pushed out


def fan_vertices(xy):
    xy = md.as_tensor(xy)
    rim3 = md.concatenate([xy, md.tensor(np.zeros((K, 1)))], axis=1)
    return md.concatenate([md.tensor(np.zeros((1, 3))), rim3], axis=0)


fan = render.Mesh(fan_vertices(true_rim), fan_faces, render.Material((0.8, 0.8, 0.8)))
flat_scene = render.Scene([fan], [render.DirectionalLight((0, 0, -1), 3.0)], flat_camera)
shape_target = render.render(flat_scene, antialias=True).data
delta = md.tensor(np.zeros((K, 2)), requires_grad=True)
LAMBDA = 1e-3
previous, following = np.roll(np.arange(K), 1), np.roll(np.arange(K), -1)


def fan_image():
    fan.vertices = fan_vertices(md.as_tensor(start_rim) + delta)
    return render.render(flat_scene, antialias=True)


def shape_loss(image, target):
    p = md.as_tensor(start_rim) + delta
    laplacian = p - (p[previous] + p[following]) * 0.5
    return render.image_loss(image, target) + LAMBDA * (laplacian**2).sum()


shape_start = fan_image().data
render.optimize(fan_image, [delta], shape_target, loss_fn=shape_loss, lr=0.01, max_iters=200,
                quiet=True)  # fmt: skip
shape_final = fan_image().data
rim_start_error = float(np.abs(start_rim - true_rim).max())
rim_error = float(np.abs(start_rim + delta.data - true_rim).max())
render.save_image(strip(shape_target, shape_start, shape_final), OUT / "shape.png")
delta = md.tensor(np.zeros((K, 2)), requires_grad=True)  # again, without the regulariser
render.optimize(fan_image, [delta], shape_target, lr=0.01, max_iters=200, quiet=True)
rim_error_unregularised = float(np.abs(start_rim + delta.data - true_rim).max())
print(f"shape: largest rim vertex error {rim_start_error:.4f} -> {rim_error:.4f} with "
      f"lambda = {LAMBDA}, {rim_error_unregularised:.1e} without")  # fmt: skip

# %% [markdown]
# The largest coordinate error of a rim vertex falls from `0.2828` <!-- check:
# rim_start_error --> to below `0.01` <!-- check: rim_error < --> (`shape.png`), under a
# quarter of a pixel (a pixel is about 0.045 wide here). *Without* the regulariser it is
# better still: below `1e-4` <!-- check: rim_error_unregularised < -->. Every rim vertex
# is a corner of the silhouette, so the image alone pins it, and the Laplacian only pulls
# the pushed-out corner towards a rounder outline than the target's. A regulariser is not
# free: it is a prior, and here the prior is wrong.
#
# It earns its place when the image does *not* pin every vertex. Take the same ellipse
# with 48 rim vertices. A vertex on a nearly straight stretch of the outline can slide
# along it without changing a single pixel: that motion is invisible, so nothing stops it,
# and the noise of the descent moves it freely. Vertices bunch up, overtake their
# neighbours, and the outline folds over itself: **crumpling**. We count folds (a turn the
# wrong way between consecutive rim edges), the ratio of the longest rim edge to the
# shortest, and the outline's largest distance from the true ellipse (relative).

# %%
FINE = 48
fine_angles = np.arange(FINE) * 2 * np.pi / FINE
fine_start = 0.5 * np.stack([np.cos(fine_angles), np.sin(fine_angles)], axis=1)
fine_true = np.stack([0.75 * np.cos(fine_angles), 0.45 * np.sin(fine_angles)], axis=1)
fine_fan = render.Mesh(
    md.concatenate([md.tensor(np.zeros((1, 3))), md.tensor(np.c_[fine_true, np.zeros(FINE)])]),
    [[0, 1 + i, 1 + (i + 1) % FINE] for i in range(FINE)], render.Material((0.8, 0.8, 0.8)),
)  # fmt: skip
fine_scene = render.Scene([fine_fan], [render.DirectionalLight((0, 0, -1), 3.0)], flat_camera)
fine_target = render.render(fine_scene, antialias=True).data
before, after = np.roll(np.arange(FINE), 1), np.roll(np.arange(FINE), -1)


def fit_fine(lam):
    d = md.tensor(np.zeros((FINE, 2)), requires_grad=True)

    def image():
        rim3 = md.concatenate([md.as_tensor(fine_start) + d, md.tensor(np.zeros((FINE, 1)))],
                              axis=1)  # fmt: skip
        fine_fan.vertices = md.concatenate([md.tensor(np.zeros((1, 3))), rim3])
        return render.render(fine_scene, antialias=True)

    def loss(image_, target):
        q = md.as_tensor(fine_start) + d
        return (
            render.image_loss(image_, target)
            + lam * ((q - (q[before] + q[after]) * 0.5) ** 2).sum()
        )

    render.optimize(image, [d], fine_target, loss_fn=loss, lr=0.01, max_iters=200, quiet=True)
    q = fine_start + d.data
    edges = np.roll(q, -1, axis=0) - q
    turns = (
        edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1]
        - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    )
    lengths = np.linalg.norm(edges, axis=1)
    outline = np.abs(np.hypot(q[:, 0] / 0.75, q[:, 1] / 0.45) - 1).max()
    return q, int((turns < 0).sum()), float(lengths.max() / lengths.min()), float(outline)


fits = {lam: fit_fine(lam) for lam in (0.0, 1e-2)}
folds_free, spacing_free, outline_free = fits[0.0][1:]
folds_reg, spacing_reg, outline_reg = fits[1e-2][1:]
closed = np.r_[np.arange(FINE), 0]
ellipse = np.linspace(0, 2 * np.pi, 200)
figure = line_figure(
    {
        "target outline": (0.75 * np.cos(ellipse), 0.45 * np.sin(ellipse)),
        "lambda = 0": (fits[0.0][0][closed, 0], fits[0.0][0][closed, 1]),
        "lambda = 0.01": (fits[1e-2][0][closed, 0], fits[1e-2][0][closed, 1]),
    },
    title="48 rim vertices fitted to a silhouette, with and without a Laplacian",
    references=("target outline",),
    size=(640, 460),
)
figure.axes[0].set_aspect("equal")
for q, colour in ((fits[0.0][0], "C0"), (fits[1e-2][0], "C1")):
    figure.axes[0].plot(q[:, 0], q[:, 1], ".", color=colour, markersize=4)  # the vertices
save_and_show(figure, OUT / "crumpling.png")
print(f"48 vertices: lambda = 0: {folds_free} folds, edge lengths {spacing_free:.1f}:1, "
      f"outline {outline_free:.4f}; lambda = 0.01: {folds_reg} folds, {spacing_reg:.2f}:1, "
      f"outline {outline_reg:.4f}")  # fmt: skip

# %% [markdown]
# Without the regulariser the 48-vertex rim ends with `9` <!-- check: folds_free -->
# folds, its longest edge `19.5` <!-- check: spacing_free --> times its shortest, and its
# outline up to `0.112` <!-- check: outline_free --> off the ellipse; with `λ = 0.01`, `0`
# <!-- check: folds_reg --> folds, a ratio of `1.4` <!-- check: spacing_reg -->, and
# `0.003` <!-- check: outline_reg --> (`crumpling.png`). The image loss is about the same
# in both (the folds are nearly invisible at this resolution): the regulariser chose among
# shapes the image cannot tell apart. That is its job, and why 3D shape fitting
# (`render.inverse.shape`: a Laplacian, or Large Steps, Nicolet et al. 2021, which
# smooths the *steps* instead of penalising the shape) needs one on any mesh finer than
# its silhouettes can pin.
#
# ## (c) A neural field for the albedo
#
# A textured plane under a point light, seen at 45°: the target's albedo is a smooth
# 64 × 64 pattern. We fit, through the renderer, a small multilayer perceptron
# `f_w: (u, v) ↦ albedo` (2 → 16 → 16 → 3, `tanh` hidden units, the output squashed into
# `(0, 1)` by `(1 + tanh)/2`), written with `md.matmul` and `md.tanh`:
#
#     h₁ = tanh(x W₁ + b₁),  h₂ = tanh(h₁ W₂ + b₂),  f = (1 + tanh(h₂ W₃ + b₃)) / 2 .
#
# The renderer looks up an albedo in a texture, so each iteration evaluates the field at
# the centres of a 16 × 16 texel grid and hands the result to the material as its texture
# (a computed tensor again); the renderer samples it bilinearly at each hit's UV. The
# network's weights are the only parameters. Geometry and visibility never change, so
# every render reuses them (`render/scene/cache.py`).

# %%
rng = np.random.default_rng(9)
plane = np.array([[-1, 0, 1], [1, 0, 1], [1, 0, -1], [-1, 0, -1]], dtype=float)
plane_uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
centres = (np.arange(64) + 0.5) / 64
U, V = np.meshgrid(centres, centres[::-1])  # row 0 of a texture is v = 1 (the top)
true_texture = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * U), 0.5 + 0.4 * np.cos(2 * np.pi * V),
                         0.3 + 0.5 * U * V], axis=-1)  # fmt: skip
board = render.Mesh(plane, [[0, 1, 2], [0, 2, 3]], render.Material((0.5, 0.5, 0.5),
                    texture=true_texture), uvs=plane_uvs)  # fmt: skip
tilted = render.Camera(position=(0, 2.2, 2.2), look_at=(0, 0, 0), up=(0, 1, 0), fov=45.0,
                       width=S, height=S)  # fmt: skip
field_scene = render.Scene([board], [render.PointLight((0.5, 2.0, 1.0), 8.0)], tilted)
field_target = render.render(field_scene).data

R, HIDDEN = 16, 16
grid = (np.arange(R) + 0.5) / R
GU, GV = np.meshgrid(grid, grid[::-1])
texel_uv = np.stack([GU.ravel(), GV.ravel()], axis=1)  # (R*R, 2), in [0, 1]
W1 = md.tensor(rng.normal(size=(2, HIDDEN)) * 1.5, requires_grad=True)
b1 = md.tensor(np.zeros(HIDDEN), requires_grad=True)
W2 = md.tensor(rng.normal(size=(HIDDEN, HIDDEN)) / 4, requires_grad=True)
b2 = md.tensor(np.zeros(HIDDEN), requires_grad=True)
W3 = md.tensor(rng.normal(size=(HIDDEN, 3)) / 4, requires_grad=True)
b3 = md.tensor(np.zeros(3), requires_grad=True)
weights = [W1, b1, W2, b2, W3, b3]
n_weights = sum(w.size for w in weights)


def field(uv):
    x = md.as_tensor(uv * 2 - 1)  # inputs in [-1, 1]
    h = md.tanh(md.matmul(x, W1) + b1)
    h = md.tanh(md.matmul(h, W2) + b2)
    return (1.0 + md.tanh(md.matmul(h, W3) + b3)) * 0.5


def field_image():
    board.material.texture = md.reshape(field(texel_uv), (R, R, 3))
    return render.render(field_scene)


field_start = field_image().data
_, field_history = render.optimize(field_image, weights, field_target, lr=0.02, max_iters=300,
                                   quiet=True)  # fmt: skip
field_final = field_image().data
field_psnr = render.psnr(np.clip(field_final, 0, 1), np.clip(field_target, 0, 1))
with md.no_grad():  # the fitted field against the true pattern, at the texel centres
    fitted = field(texel_uv).data
true_at_texels = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * GU.ravel()),
                           0.5 + 0.4 * np.cos(2 * np.pi * GV.ravel()),
                           0.3 + 0.5 * GU.ravel() * GV.ravel()], axis=1)  # fmt: skip
field_albedo_rms = float(np.sqrt(((fitted - true_at_texels) ** 2).mean()))
print(f"neural field: {n_weights} weights; loss {field_history.loss[0]:.2e} -> "
      f"{field_history.loss[-1]:.2e}; PSNR {field_psnr:.1f} dB; albedo RMS error at the "
      f"texel centres {field_albedo_rms:.4f}")  # fmt: skip
render.save_image(strip(field_target, field_start, field_final), OUT / "field_renders.png")
texture_pair = np.concatenate([true_texture[::4, ::4], fitted.reshape(R, R, 3)], axis=1)
render.save_image(np.repeat(np.repeat(np.clip(texture_pair, 0, 1), 8, 0), 8, 1),
                  OUT / "field_texture.png")  # fmt: skip
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# The network has `371` <!-- check: n_weights --> weights. After 300 Adam steps its render
# matches the target to a PSNR above `40` <!-- check: field_psnr > --> dB
# (`field_renders.png`: target, start, result), and the field itself, never compared
# with the texture directly, matches the true pattern at the texel centres to an RMS error
# below `0.05` <!-- check: field_albedo_rms < --> (`field_texture.png`: truth, fit). The
# albedo can be recovered because the image is linear in it at every lit point of the
# plane, and here all of the plane is lit and in view.
#
# ## Exercises
#
# 1. In (a), add a uniform scale `σ` of the teapot (start at 1, target 1.1) to the pose.
#    Which of the parameters is recovered worst, and why?
# 2. In (b), fit the 48-vertex rim with `λ = 1e-3` and `λ = 1`. Report the folds, the
#    spacing ratio and the outline error for both, and explain the trade-off.
# 3. In (c), replace the network by a plain 16 × 16 texture of free parameters (768
#    numbers) initialised at 0.5, projected to `[0, 1]` (`md.optim.box`). Compare the
#    PSNR after 300 steps. Which texels stay at their start, and why?
#
# Solutions: `lessons/solutions/09_beyond.py`.
