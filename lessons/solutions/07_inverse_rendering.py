# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 7 (inverse rendering)

# %%
import numpy as np

import minidiff as md
import render
from render.inverse import experiments

SIZE = 48
# The lesson's problem, as render.inverse.experiments sets it up.
scene, (position, intensity), target = experiments.light_estimation_problem(SIZE, 42)
start_position, start_intensity = position.data.copy(), intensity.item()


def restart():
    position.data, intensity.data = start_position.copy(), np.array(start_intensity)


# %% [markdown]
# ## Exercise 1: plain gradient descent
#
# At the start, `∂L/∂position` is of order `5e-3` and `∂L/∂intensity` of order `1.5e-4`,
# while the intensity must move by about 85 and the position by a few units. SGD's step is
# `lr · g`: a rate that moves the position sensibly (100) moves the intensity by a few
# hundredths per step, and one large enough for the intensity throws the light away. Two
# rates, `(100, 1e4)`, do much better, but after 300 steps the light is still a few percent
# off; Adam, whose steps are normalised per parameter, gets to 0.06 % (lesson 7).

# %%
restart()
L = render.image_loss(render.render(scene), target)
L.backward()
print(f"gradients at the start: position {position.grad}, intensity {intensity.grad:.2e}")
results = {}
for lr in (100.0, [100.0, 1e4]):
    restart()
    sgd = md.optim.SGD([position, intensity], lr=lr)
    _, history = render.optimize(scene, [position, intensity], target, optimizer=sgd,
                                 max_iters=300, quiet=True)  # fmt: skip
    error = experiments.relative_error_pct(position.data, experiments.TRUE_LIGHT)
    results[str(lr)] = (history.loss[-1], error, intensity.item())
    print(f"SGD lr={lr}: loss {history.loss[-1]:.2e}, position error {error:.1f} %, "
          f"intensity {intensity.item():.1f}")  # fmt: skip
one, two = results["100.0"], results["[100.0, 10000.0]"]
assert abs(one[2] - start_intensity) < 5  # one rate: the intensity hardly moves
assert two[0] < one[0] / 5 and two[1] < one[1]  # two rates: better
assert two[1] > 0.5  # but far from Adam's 0.06 %

# %% [markdown]
# ## Exercise 2: optimising at a lower resolution
#
# With one sample per pixel, a 24 × 24 pixel sees the scene through its centre, while the
# averaged target pixel is the mean of four 48 × 48 pixel centres: at every silhouette,
# crease and shading gradient the two differ, the loss's minimum is no longer at the true
# light, and the fit ends far off (about 20 %). With `spp=4` the renderer's stratified
# 2 × 2 samples of a 24 × 24 pixel are exactly the centres of the four 48 × 48 pixels it
# covers, so the render of the truth *is* the averaged target (difference 0) and the
# light is found.

# %%
small_target = target.reshape(24, 2, 24, 2, 3).mean(axis=(1, 3))
small_truth = render.paper_scene(24, 24, light_position=experiments.TRUE_LIGHT,
                                 light_intensity=experiments.TRUE_INTENSITY)  # fmt: skip
assert np.abs(render.render(small_truth, spp=4).data - small_target).max() < 1e-14
small_errors = {}
for spp in (1, 4):
    restart()
    small_scene = render.paper_scene(24, 24, light_position=position, light_intensity=intensity)
    render.optimize(small_scene, [position, intensity], small_target, lr=[0.3, 20.0],
                    max_iters=300, quiet=True, render_kwargs={"spp": spp})  # fmt: skip
    small_errors[spp] = experiments.relative_error_pct(position.data, experiments.TRUE_LIGHT)
    print(f"24 x 24, spp={spp}, against the averaged target: position error "
          f"{small_errors[spp]:.2f} %, intensity {intensity.item():.2f}")  # fmt: skip
assert small_errors[1] > 5.0 and small_errors[4] < 1.0

# %% [markdown]
# ## Exercise 3: a callback
#
# The callback sees the iteration, the loss, the image and the `History`, whose
# `params[-1]` are the parameters the loss was computed at.

# %%
restart()
errors = []


def record_error(it, loss, image, history):
    errors.append(experiments.relative_error_pct(history.params[-1][0], experiments.TRUE_LIGHT))


render.optimize(scene, [position, intensity], target, lr=[0.3, 20.0], max_iters=300, quiet=True,
                callback=record_error)  # fmt: skip
first_below_1pct = int(np.flatnonzero(np.array(errors) < 1.0)[0])
print(f"position error below 1 % first at iteration {first_below_1pct}")
assert 0 < first_below_1pct < 300
