# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 10 (Monte Carlo)

# %%
import math

import numpy as np

import minidiff as md
from render.path import render_path
from render.path.sample.random import uniform
from render.path.sample.sampling import cosine_hemisphere
from render.scene.cornell import cornell_box

# %% [markdown]
# ## Exercise 1: a uniform sky
#
# With `L = 1`, `E = ∫ cos θ dω = π`. A cosine-weighted sample is `L cos θ / (cos θ / π) =
# π`: the density is exactly proportional to the integrand, so every sample *is* the answer
# (zero variance: perfect importance sampling). A uniform sample is `2π cos θ` with
# `cos θ` uniform in `[0, 1]`: mean `π`, relative variance `E[(2 cos θ)²] − 1 = 4/3 − 1`,
# relative standard deviation `1/√3 ≈ 0.577`.

# %%
ids = np.arange(100_000)
u1, u2 = uniform(11, ids, 0), uniform(11, ids, 1)
cos = cosine_hemisphere(u1, u2, np.tile([0.0, 0.0, 1.0], (len(ids), 1))).data[:, 2]
cosine_samples = 1.0 * cos / (cos / math.pi)  # L cos / p with L = 1, p = cos / pi
uniform_samples = 1.0 * u1 / (1 / (2 * math.pi))  # cos theta = u1 uniform, p = 1 / (2 pi)
relative_std = uniform_samples.std() / math.pi
print(f"cosine: relative std {cosine_samples.std() / math.pi:.2e}; uniform: mean / pi "
      f"{uniform_samples.mean() / math.pi:.4f}, relative std {relative_std:.4f}")  # fmt: skip
assert cosine_samples.std() < 1e-15 * math.pi
assert abs(uniform_samples.std() / math.pi - 1 / math.sqrt(3)) < 0.01

# %% [markdown]
# ## Exercise 2: how many samples for 5 % noise?
#
# The noise falls as `1/√spp`, so from a noise `σ₁₆` at 16 spp the spp for 5 % is
# `16 (σ₁₆ / 0.05)²`.

# %%
room = cornell_box(12, 12)


def relative_noise(spp: int, seeds: int = 6) -> float:
    with md.no_grad():
        images = np.stack([render_path(room, spp=spp, max_depth=4, seed=s).data
                           for s in range(seeds)])  # fmt: skip
    return float((images.std(axis=0, ddof=1) / images.mean(axis=0).clip(1e-3)).mean())


noise_16 = relative_noise(16)
needed = math.ceil(16 * (noise_16 / 0.05) ** 2)
measured = relative_noise(needed)
print(f"noise at 16 spp {noise_16:.4f}: predicted {needed} spp for 5 %; measured {measured:.4f}")
assert abs(measured - 0.05) < 0.01

# %% [markdown]
# ## Exercise 3: the balance heuristic
#
# `w_i = p_i / (p_1 + p_2)` also sums to one for every direction, so the estimator stays
# unbiased. But on the small lamp it is far noisier than the power heuristic (about 0.056
# against 0.002 per sample): a rare BSDF sample that hits the lamp keeps a weight of a few
# per cent of its huge value `π L_e`, where the power heuristic's squares shrink that
# weight to almost nothing and leave the lamp to light sampling. That is why Veach
# recommends the power heuristic (with exponent 2) when one technique is much better than
# the other; on the large lamp the two are close.


# %%
def lamp(half: float, n: int, power: float) -> np.ndarray:
    """One-sample MIS estimates of the lamp's irradiance, weights p^power / sum p^power."""
    ids = np.arange(n)
    area = (2 * half) ** 2
    point = np.stack([half * (2 * uniform(3, ids, 0) - 1), half * (2 * uniform(3, ids, 1) - 1),
                      np.ones(n)], axis=1)  # fmt: skip
    r2 = (point**2).sum(axis=1)
    cos_here = point[:, 2] / np.sqrt(r2)
    p_light = r2 / (cos_here * area)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    w = cosine_hemisphere(uniform(3, ids, 2), uniform(3, ids, 3), up).data
    t = 1.0 / np.maximum(w[:, 2], 1e-300)
    hits = (np.abs(w[:, 0] * t) < half) & (np.abs(w[:, 1] * t) < half)
    p_bsdf = w[:, 2] / math.pi
    p_light_there = np.where(hits, (t**2 * (w**2).sum(1)) / (w[:, 2] * area), 0.0)
    w_light = p_light**power / (p_light**power + (cos_here / math.pi) ** power)
    w_bsdf = np.where(hits, p_bsdf**power / (p_bsdf**power + p_light_there**power), 0.0)
    return w_light * cos_here / p_light + w_bsdf * np.where(hits, math.pi, 0.0)


for half, exact in ((0.05, 0.009967), (2.0, 2.610753)):  # lesson 10's closed forms
    power, balance = lamp(half, 200_000, 2.0), lamp(half, 200_000, 1.0)
    print(f"half-side {half}: mean / exact power {power.mean() / exact:.4f}, balance "
          f"{balance.mean() / exact:.4f}; relative std power {power.std() / exact:.3f}, "
          f"balance {balance.std() / exact:.3f}")  # fmt: skip
    assert abs(balance.mean() / exact - 1) < 0.01  # unbiased too
    if half < 1:
        assert balance.std() > 10 * power.std()  # the small lamp: far noisier
        # The numbers the text states (relative std of one estimate).
        assert (round(balance.std() / exact, 3), round(power.std() / exact, 3)) == (0.056, 0.002)
    else:
        assert abs(balance.std() / power.std() - 1) < 0.2  # the large lamp: close

# %% [markdown]
# ## Exercise 4: antithetic sampling and a control variate for a derivative
#
# `I'(θ) = ∫₀¹ x e^(θx) dx = (θe^θ − e^θ + 1)/θ²`. The plain estimator averages
# `2n` evaluations at independent `x`; the antithetic one averages `n` pairs
# `(f(x) + f(1 − x))/2` (the same `2n` evaluations). For an integrand that is monotone in
# `x`, `f(x)` and `f(1 − x)` are negatively correlated, so the pair's mean varies less than
# two independent samples' would. The control variate subtracts `c (g(x) − E[g])`, which has
# mean zero (so no bias), and with `c = Cov(f, g) / Var(g)` removes the part of `f`'s noise
# that `g` explains. (Estimating `c` from the same samples adds a bias of order `1/n`; a
# fixed `c` has none.)

# %%
theta, n = 1.5, 100_000
exact_derivative = (theta * math.exp(theta) - math.exp(theta) + 1) / theta**2
xs = uniform(21, np.arange(2 * n), 0)


def integrand(x):
    return x * np.exp(theta * x)


plain_samples = integrand(xs)  # 2n evaluations
pairs = (integrand(xs[:n]) + integrand(1 - xs[:n])) / 2  # n pairs: 2n evaluations
g, g_mean = xs + theta * xs**2, 0.5 + theta / 3
c = np.cov(plain_samples, g)[0, 1] / g.var(ddof=1)
controlled = plain_samples - c * (g - g_mean)  # 2n evaluations (g is nearly free)

variance_of_mean = {
    "plain": plain_samples.var() / (2 * n),
    "antithetic": pairs.var() / n,
    "control variate": controlled.var() / (2 * n),
}
antithetic_gain = float(variance_of_mean["plain"] / variance_of_mean["antithetic"])
control_gain = float(variance_of_mean["plain"] / variance_of_mean["control variate"])
for name, estimate in (("plain", plain_samples), ("antithetic", pairs),
                       ("control variate", controlled)):  # fmt: skip
    error = (estimate.mean() - exact_derivative) / math.sqrt(variance_of_mean[name])
    print(f"{name:16s} {estimate.mean():.6f} (exact {exact_derivative:.6f}, {error:+.2f} "
          f"standard errors)")  # fmt: skip
    assert abs(error) < 4  # unbiased
print(f"variance of the estimate, at equal cost: antithetic / {antithetic_gain:.1f}, "
      f"control variate / {control_gain:.1f}")  # fmt: skip
assert antithetic_gain > 2 and control_gain > 10
assert round(antithetic_gain, 1) == 6.5 and control_gain > 50  # the numbers stated below

# %% [markdown]
# At equal cost the antithetic pairs divide the variance by `6.5`
# <!-- check: antithetic_gain -->, the control variate by more than `50`
# <!-- check: control_gain > -->. In a renderer, antithetic pairs are mirrored sample
# positions in a pixel or mirrored directions about a normal, and a control variate is an
# approximation whose integral is known: a light's unshadowed irradiance, or the previous
# iteration's image in an optimisation (the estimate then only carries the noise of the
# *change*).
