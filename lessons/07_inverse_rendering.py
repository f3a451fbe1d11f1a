# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 7 — Inverse rendering
#
# Lesson 6 gave us `∂I/∂θ` for every continuous parameter. Inverse rendering turns it
# around: given a photograph `T`, find the parameters `θ` whose render matches it. The
# paper's Algorithm 1 is gradient descent on an image loss,
#
#     L(θ) = (1/3HW) Σ (clip(I(θ), 0, 1) − T)²          (Eq. 1, `render.image_loss`)
#
#     repeat:  I ← render(θ);  L ← loss(I, T);  g ← ∂L/∂θ (backward);  θ ← Adam(θ, g)
#
# with Adam (Eq. 2, `minidiff.optim.Adam`): a step of size about `lr` per parameter along
# the sign of a running mean of the gradient, scaled by a running root mean square,
#
#     m ← β₁m + (1−β₁)g,   v ← β₂v + (1−β₂)g²,   θ ← θ − lr · m̂ / (√v̂ + ε)
#
# (`m̂, v̂` bias-corrected). Because the step is normalised, `lr` is in the parameter's own
# units: a light position in metres and an intensity in hundreds get their own `lr`.
# The clip in Eq. 1 is what a camera or an 8-bit file records; saturated pixels pass no
# gradient.

# %%
import time

import numpy as np
from course import figures_folder, save_and_show

import minidiff as md
import render
from render.inverse import experiments
from render.inverse.plot import line_figure

# This lesson's figures go to out/lessons/07_inverse_rendering/ (or under $LESSONS_OUT).
OUT = figures_folder("07_inverse_rendering")
SIZE = 48
lesson_start = time.perf_counter()


def upscale(image, factor=4):
    return np.repeat(np.repeat(np.clip(image, 0, 1), factor, 0), factor, 1)


# %% [markdown]
# ## Algorithm 1 by hand: a light
#
# The target is the paper's teapot lit by a point light at `(1, 4, 2)` with intensity 150,
# 48 × 48 pixels. We start from the paper's seeded guess
# (`experiments.light_estimation_start(42)`: the light far off, the intensity wrong) and
# make the light's position and intensity leaves that require a gradient.

# %%
truth = render.paper_scene(SIZE, SIZE, light_position=experiments.TRUE_LIGHT,
                           light_intensity=experiments.TRUE_INTENSITY)  # fmt: skip
target = render.render(truth).data
start_position, start_intensity = experiments.light_estimation_start(42)
position = md.tensor(start_position, requires_grad=True)
intensity = md.tensor(start_intensity, requires_grad=True)
scene = render.paper_scene(SIZE, SIZE, light_position=position, light_intensity=intensity)
initial_image = render.render(scene).data
print(f"start: light {start_position.round(3)}, intensity {start_intensity:.2f}")

ITERS = 300
adam = md.optim.Adam([position, intensity], lr=[0.3, 20.0])
losses = []
for _ in range(ITERS):
    adam.zero_grad()  # gradients accumulate: clear them first
    image = render.render(scene)  # render
    loss = render.image_loss(image, target)  # Eq. 1
    loss.backward()  # dL/dposition, dL/dintensity
    adam.step()  # Eq. 2
    losses.append(loss.item())
final_image = render.render(scene).data
position_error = experiments.relative_error_pct(position.data, experiments.TRUE_LIGHT)
intensity_error = 100 * abs(intensity.item() - 150.0) / 150.0
print(f"after {ITERS} steps: light {position.data.round(4)}, intensity {intensity.item():.3f}")
print(f"loss {losses[0]:.2e} -> {losses[-1]:.2e}; position error {position_error:.3f} %, "
      f"intensity error {intensity_error:.3f} %")  # fmt: skip
start_error_pct = experiments.relative_error_pct(start_position, experiments.TRUE_LIGHT)
loss_drop = losses[0] / losses[-1]

# %% [markdown]
# Five lines in the loop. The light starts `83.7` <!-- check: start_error_pct --> % of
# `|(1, 4, 2)|` away from the truth; after 300 steps its position is within `0.5`
# <!-- check: position_error < --> % and its intensity within `0.5`
# <!-- check: intensity_error < --> % (the printout has the digits), and the loss fell
# by more than a factor `1e5` <!-- check: loss_drop > -->.


# %% [markdown]
# ## The same with `render.optimize`
#
# `render.optimize(scene, params, target, lr=...)` is that loop, plus bookkeeping: a
# `History` of the loss and the parameters at every iteration, a tolerance to stop at,
# an optional projection after each step (`md.optim.box(0, 1)` keeps an albedo in range),
# `render_kwargs` for the renderer (lesson 8 passes `antialias=True`) and an error that
# says which iteration produced a NaN. From the same start it must retrace our loop step
# for step.

# %%
position_b = md.tensor(start_position, requires_grad=True)
intensity_b = md.tensor(start_intensity, requires_grad=True)
scene_b = render.paper_scene(SIZE, SIZE, light_position=position_b, light_intensity=intensity_b)
_, history = render.optimize(scene_b, [position_b, intensity_b], target, lr=[0.3, 20.0],
                             max_iters=ITERS, quiet=True)  # fmt: skip
# history.loss[i] is the loss before update i; it has one more entry (the final loss).
same_trajectory = float(np.abs(np.array(history.loss[:ITERS]) - losses).max())
same_light = float(np.abs(position_b.data - position.data).max())
history_iterations = history.iterations
print(f"render.optimize: {history.iterations} updates, largest loss difference to the "
      f"hand-written loop {same_trajectory}, light difference {same_light}")  # fmt: skip

# %% [markdown]
# It made `300` <!-- check: history_iterations --> updates and its losses differ from ours
# by exactly `0` <!-- check: same_trajectory -->: the same computation.
#
# ## A plateau, and what it is made of
#
# The light's loss falls fast, then sits near `2e-4` for about a hundred iterations, then
# drops by a factor of twenty in one step. That is not Adam being slow. `history.params`
# holds the parameters at every iteration: render them with `return_info=True` and compare
# each pixel's *shadow decision* (`info.lit`, lesson 6: a constant on the tape) with the
# target's, on the pixels that see the same primitive in both.

# %%
_, target_info = render.render(truth, return_info=True)


def shadow_mismatch(iteration):
    """Pixels whose shadow decision differs from the target's at ``iteration``, and their
    share of the squared error."""
    light_at, intensity_at = history.params[iteration]
    at = render.paper_scene(SIZE, SIZE, light_position=light_at, light_intensity=intensity_at)
    rendered, info = render.render(at, return_info=True)
    same_surface = info.prim_id[..., 0] == target_info.prim_id[..., 0]
    differ = (info.lit != target_info.lit).any(axis=0)[..., 0] & same_surface
    error = ((rendered.data - target) ** 2).sum(-1)
    return int(differ.sum()), float(error[differ].sum() / error.sum())


loss_history = np.array(history.loss)
step_drop = loss_history[:-1] / loss_history[1:]  # update i takes loss[i] to loss[i + 1]
flip_update = int(np.argmax(step_drop))
flip_drop = float(step_drop[flip_update])
plateau_pixels, plateau_share = shadow_mismatch(flip_update - 40)
before_pixels, before_share = shadow_mismatch(flip_update)
after_pixels, _ = shadow_mismatch(flip_update + 1)
print(f"largest drop: update {flip_update}, loss / {flip_drop:.1f}; pixels in the wrong "
      f"shadow: {plateau_pixels} at iteration {flip_update - 40} ({plateau_share:.0%} of the "
      f"loss), {before_pixels} just before ({before_share:.0%}), {after_pixels} after")  # fmt: skip

# %% [markdown]
# The largest one-step drop is update `146` <!-- check: flip_update -->, by a factor of
# `20.6` <!-- check: flip_drop -->. Forty iterations before it exactly `1`
# <!-- check: plateau_pixels --> pixel is in shadow in one image and lit in the other, and
# that single pixel holds more than `0.75` <!-- check: plateau_share > --> of the loss (just
# before the flip, more than `0.85` <!-- check: before_share > -->); after it, `0`
# <!-- check: after_pixels --> pixels differ. The gradient cannot see that pixel's problem:
# its shadow decision is a constant on the tape, so the pixel's derivative is that of its
# shading with the decision held (zero where it is in shadow: nothing there depends on the
# light), never "move the shadow's edge across it". The light drifts, pulled by the other
# pixels, until the shadow ray happens to change its answer, and the loss collapses. A
# visibility decision that matters to the loss but has no gradient is the subject of
# lesson 8.
#
# ## A material, and briefly a camera
#
# `render/inverse/experiments.py` holds the paper's problems as functions returning an
# `ExperimentRun` (`.metrics`, `.history`, `.target`, `.initial`, `.final`).
# `run_material_recovery` recovers the teapot's albedo (a random colour, seeded) from a
# random start, projected onto `[0, 1]³`. The image is linear in the albedo and nothing
# else moves, so the renderer reuses its visibility and surfaces from one iteration to the
# next (`render/scene/cache.py`) and the problem is easy.
#
# A camera is harder: moving it moves every silhouette, and silhouettes are exactly what
# the plain renderer's gradient ignores (lesson 8). Here we move only its position,
# `0.3` along x and y, and keep it looking at the teapot.

# %%
material = experiments.run_material_recovery(size=SIZE, iters=100)
albedo_error = material.metrics["final_rgb_error"]
albedo_start_error = material.metrics["initial_rgb_error"]
print(f"albedo: true {np.round(material.metrics['true_albedo'], 4)}, found "
      f"{np.round(material.metrics['final_albedo'], 4)}, RGB error "
      f"{material.metrics['initial_rgb_error']:.3f} -> {albedo_error:.1e}")  # fmt: skip

camera_position = md.tensor([3.3, 2.3, 5.0], requires_grad=True)
camera_scene = render.paper_scene(SIZE, SIZE, camera_position=camera_position)
camera_target = render.render(render.paper_scene(SIZE, SIZE)).data
camera_initial = render.render(camera_scene).data
_, camera_history = render.optimize(camera_scene, [camera_position], camera_target, lr=0.02,
                                    max_iters=150, quiet=True)  # fmt: skip
camera_error = experiments.relative_error_pct(camera_position.data, experiments.TRUE_CAMERA)
camera_start_error = experiments.relative_error_pct(np.array([3.3, 2.3, 5.0]),
                                                    experiments.TRUE_CAMERA)  # fmt: skip
camera_final = render.render(camera_scene).data
print(f"camera: {camera_position.data.round(4)}, error {camera_start_error:.2f} % -> "
      f"{camera_error:.3f} %")  # fmt: skip

# %% [markdown]
# The albedo's RGB error (the distance between the colours) falls from `0.404`
# <!-- check: albedo_start_error --> to below `5e-3` <!-- check: albedo_error < --> in 100
# steps. The camera's position error falls from `6.88` <!-- check: camera_start_error --> %
# to below `0.2` <!-- check: camera_error < --> % in 150 steps: the shading of the teapot's
# faces changes with the viewpoint (through the hit points lesson 6 recomputes on the
# tape), and that is enough here. Lesson 8 shows a camera problem where it is not.
#
# ## Figures
#
# `loss_curves.png`: the three losses on a log scale. They are not monotone: the dips and
# bumps are Adam overshooting and turning round (its step does not shrink with the
# gradient, only with the gradient's running mean). The light's plateau and its cliff are
# the one pixel in the wrong shadow above; the exercises and lesson 8 show how much a loss
# curve's shape depends on the start and on what the gradient can see.
# `before_after.png`: per row target, start, result, for the light, the material and the
# camera (sRGB).

# %%
figure = line_figure(
    {
        "light (position + intensity)": (np.arange(ITERS), losses),
        "albedo": (np.arange(len(material.history.loss)), material.history.loss),
        "camera position": (np.arange(len(camera_history.loss)), camera_history.loss),
    },
    title="Algorithm 1 on three problems (48 x 48)",
    xlabel="iteration",
    ylabel="loss (Eq. 1)",
    logy=True,
)
save_and_show(figure, OUT / "loss_curves.png")
rows = [
    [target, initial_image, final_image],
    [material.target, material.initial, material.final],
    [camera_target, camera_initial, camera_final],
]
grid = np.concatenate([np.concatenate([upscale(im) for im in row], axis=1) for row in rows])
render.save_image(grid, OUT / "before_after.png", srgb=True)
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. Run the light problem with plain gradient descent (`md.optim.SGD`) instead of Adam.
#    Why does one learning rate for the position and the intensity not work (look at the
#    sizes of the two gradients), and how far does a pair of rates get in 300 steps,
#    compared with Adam?
# 2. Recover the light from the 48 × 48 target while optimising at 24 × 24: average the
#    target's 2 × 2 blocks, and render the 24 × 24 scene with `spp=1`, then with `spp=4`.
#    Why is the first so far off, and why does the second match the averaged target?
# 3. Use `render.optimize`'s `callback` to record the light position at every iteration
#    and report the first iteration at which the position error drops below 1 %.
#
# Solutions: `lessons/solutions/07_inverse_rendering.py`.
