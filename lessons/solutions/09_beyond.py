# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 9 (pose, shape, a neural field)
#
# The lesson's three set-ups, repeated so that this file runs on its own.

# %%
import math

import numpy as np

import minidiff as md
import render

S = 48

# %% [markdown]
# ## Exercise 1: pose and scale
#
# The vertices become `σ · R(θ) V₀ + t`. Measured after 200 steps: the angle within about
# 0.01°, the scale within 0.003, the translation within about 0.01, worst in `z`. The
# translation is the weak one: a larger teapot and a nearer one look much alike (both
# grow the silhouette; only the perspective and the shading tell them apart), so the
# scale and the translation towards the camera share a flat valley of the loss, and in
# that valley the optimiser settles the scale first, the translation last. (Adding the
# scale even helped the angle here: lesson 9's pose without it stopped 0.6° short.)

# %%
scene = render.paper_scene(S, S)
teapot = scene.objects[0]
rest = teapot.vertices.data.copy()
X, Y, Z = rest[:, 0], rest[:, 1], rest[:, 2]


def posed(theta, t, sigma):
    c, s = md.cos(theta), md.sin(theta)
    return md.stack([(c * X + s * Z) * sigma + t[0], Y * sigma + t[1],
                     (-s * X + c * Z) * sigma + t[2]], axis=1)  # fmt: skip


true_theta, true_t, true_sigma = math.radians(25.0), np.array([0.15, 0.0, -0.1]), 1.1
with md.no_grad():
    teapot.vertices = posed(md.tensor(true_theta), md.tensor(true_t), md.tensor(true_sigma))
    target = render.render(scene, antialias=True).data
theta = md.tensor(0.0, requires_grad=True)
t = md.tensor(np.zeros(3), requires_grad=True)
sigma = md.tensor(1.0, requires_grad=True)


def image():
    teapot.vertices = posed(theta, t, sigma)
    return render.render(scene, antialias=True)


render.optimize(image, [theta, t, sigma], target, lr=0.02, max_iters=200, quiet=True)
angle_error = abs(math.degrees(theta.item() - true_theta))
t_error = np.abs(t.data - true_t)
sigma_error = abs(sigma.item() - true_sigma)
print(f"angle error {angle_error:.2f} deg, translation error {t_error.round(4)}, "
      f"scale error {sigma_error:.4f}")  # fmt: skip
assert angle_error < 1.0 and sigma_error < 0.01 and t_error.max() < 0.05

# %% [markdown]
# ## Exercise 2: the regulariser's weight on the 48-vertex rim
#
# Too weak (`λ = 1e-3`) and the rim still crumples: the Laplacian's pull is smaller than the
# descent's noise along the outline. `λ = 1` keeps the vertices evenly spaced and on the
# ellipse, even better than `λ = 0.01`: the truth here *is* smooth and evenly sampled, so
# a strong smoothness prior costs nothing. On a shape with a sharp feature (the lesson's
# 8-vertex fan with one corner pushed out) the same prior pulls the feature in: the right
# weight depends on how smooth the truth is, which is why it is a hyperparameter.

# %%
FINE = 48
angles = np.arange(FINE) * 2 * np.pi / FINE
start = 0.5 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
truth = np.stack([0.75 * np.cos(angles), 0.45 * np.sin(angles)], axis=1)
camera = render.Camera(position=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov=40.0,
                       width=S, height=S)  # fmt: skip
fan = render.Mesh(
    md.concatenate([md.tensor(np.zeros((1, 3))), md.tensor(np.c_[truth, np.zeros(FINE)])]),
    [[0, 1 + i, 1 + (i + 1) % FINE] for i in range(FINE)], render.Material((0.8, 0.8, 0.8)),
)  # fmt: skip
flat = render.Scene([fan], [render.DirectionalLight((0, 0, -1), 3.0)], camera)
target = render.render(flat, antialias=True).data
before, after = np.roll(np.arange(FINE), 1), np.roll(np.arange(FINE), -1)
results = {}
for lam in (1e-3, 1.0):
    d = md.tensor(np.zeros((FINE, 2)), requires_grad=True)

    def image(d=d):
        rim3 = md.concatenate([md.as_tensor(start) + d, md.tensor(np.zeros((FINE, 1)))], axis=1)
        fan.vertices = md.concatenate([md.tensor(np.zeros((1, 3))), rim3])
        return render.render(flat, antialias=True)

    def loss(image_, target_, d=d, lam=lam):
        q = md.as_tensor(start) + d
        smooth = ((q - (q[before] + q[after]) * 0.5) ** 2).sum()
        return render.image_loss(image_, target_) + lam * smooth

    render.optimize(image, [d], target, loss_fn=loss, lr=0.01, max_iters=200, quiet=True)
    q = start + d.data
    edges = np.roll(q, -1, axis=0) - q
    nxt = np.roll(edges, -1, axis=0)
    folds = int(((edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]) < 0).sum())
    lengths = np.linalg.norm(edges, axis=1)
    outline = float(np.abs(np.hypot(q[:, 0] / 0.75, q[:, 1] / 0.45) - 1).max())
    results[lam] = (folds, float(lengths.max() / lengths.min()), outline)
    print(f"lambda = {lam}: {folds} folds, edge lengths {results[lam][1]:.2f}:1, "
          f"outline error {outline:.4f}")  # fmt: skip
assert results[1e-3][0] > 0 and results[1.0][0] == 0
assert results[1.0][2] < results[1e-3][2]

# %% [markdown]
# ## Exercise 3: free texels instead of a network
#
# 16 × 16 × 3 = 768 free numbers fit the render at least as well as the 371 weights: the
# image is linear in each texel, and Adam moves each one on its own. A texel stays at its
# start only if no hit's bilinear lookup uses it, which here (the whole plane in view)
# happens to none. What the network adds is not accuracy but a prior: its smooth function
# fills in texels the camera never sees, where free texels would stay at 0.5.

# %%
plane = np.array([[-1, 0, 1], [1, 0, 1], [1, 0, -1], [-1, 0, -1]], dtype=float)
centres = (np.arange(64) + 0.5) / 64
U, V = np.meshgrid(centres, centres[::-1])
true_texture = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * U), 0.5 + 0.4 * np.cos(2 * np.pi * V),
                         0.3 + 0.5 * U * V], axis=-1)  # fmt: skip
board = render.Mesh(plane, [[0, 1, 2], [0, 2, 3]],
                    render.Material((0.5, 0.5, 0.5), texture=true_texture),
                    uvs=[[0, 0], [1, 0], [1, 1], [0, 1]])  # fmt: skip
tilted = render.Camera(position=(0, 2.2, 2.2), look_at=(0, 0, 0), up=(0, 1, 0), fov=45.0,
                       width=S, height=S)  # fmt: skip
field_scene = render.Scene([board], [render.PointLight((0.5, 2.0, 1.0), 8.0)], tilted)
target = render.render(field_scene).data
texels = md.tensor(np.full((16, 16, 3), 0.5), requires_grad=True)
board.material.texture = texels
render.optimize(field_scene, [texels], target, lr=0.02, max_iters=300, quiet=True,
                project=md.optim.box(0.0, 1.0))  # fmt: skip
free_psnr = render.psnr(np.clip(render.render(field_scene).data, 0, 1), np.clip(target, 0, 1))
untouched = int((texels.data == 0.5).all(axis=-1).sum())
print(f"free texels: PSNR {free_psnr:.1f} dB; {untouched} texels still at their start")
assert free_psnr > 40.0
