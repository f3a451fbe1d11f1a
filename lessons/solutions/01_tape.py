# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 1 (a tape from scratch)
#
# The lesson's `Value` (run from the lesson's file), with the additions of exercise 1
# (`tanh`, `__pow__`) and, for exercise 2, a `topological_order` that forgets `seen`.

# %%
import math
import sys
from pathlib import Path

import numpy as np

import minidiff as md
from minidiff.tensor import as_tensor, record

# lessons/ is this file's grandparent; in Jupyter (no __file__) the notebook's folder.
here = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
sys.path.insert(0, str(here.parent))  # lessons/course.py
from course import run_lesson  # noqa: E402

Value = run_lesson("01_tape")["Value"]


# Exercise 1: two more operations, each a value and its local derivative. They are added to
# the lesson's class itself, so that the values its own operations build have them too.
def tanh(self):
    t = math.tanh(self.data)
    return Value(t, (self,), (1.0 - t * t,))


def power(self, k):  # a constant exponent
    return Value(self.data**k, (self,), (k * self.data ** (k - 1),))


Value.tanh, Value.__pow__ = tanh, power


# %% [markdown]
# ## Exercise 1
#
# `g(x) = tanh(x)³ + x²`, `g'(x) = 3 tanh(x)² (1 − tanh(x)²) + 2x`.

# %%
x = Value(0.7)
g = x.tanh() ** 3 + x**2
g.backward()


def g_float(v):
    return math.tanh(v) ** 3 + v**2


h = 1e-5
fd = (g_float(0.7 + h) - g_float(0.7 - h)) / (2 * h)
t = math.tanh(0.7)
exact = 3 * t**2 * (1 - t**2) + 2 * 0.7
print(f"tape {x.grad:.10f}  central difference {fd:.10f}  by hand {exact:.10f}")
assert abs(x.grad - exact) < 1e-14 and abs(fd - exact) < 1e-9

# %% [markdown]
# ## Exercise 2
#
# Without `seen`, `visit` walks every *path* from the output to the leaves: `a + a` lists its
# parent twice, so after ten doublings `x` is reached along 2¹⁰ paths, every intermediate
# value is listed (and its `_backward` run) once per path to it, and each run adds its whole
# `grad` again. The number of calls grows as 2ⁿ and the gradient is wrong.


# %%
def order_forgetting_seen(self):
    """The lesson's `topological_order` with a `visit` that forgets `seen`."""
    order = []

    def visit(v):  # a value is appended once per path from the output to it
        for p in v.parents:
            visit(p)
        order.append(v)

    visit(self)
    return order


lesson_order = Value.topological_order
for dedupe, order in ((True, lesson_order), (False, order_forgetting_seen)):
    Value.topological_order = order
    x = Value(1.0)
    a = x
    for _ in range(10):
        a = a + a
    a.backward()
    calls = len(a.topological_order())  # backward runs one _backward per entry
    print(f"dedupe={dedupe!s:<5}: x.grad = {x.grad:>10.0f}, _backward calls = {calls}")
    if dedupe:
        assert x.grad == 1024 and calls == 11
    else:
        assert x.grad != 1024 and calls == 2**11 - 1
Value.topological_order = lesson_order

# %% [markdown]
# ## Exercise 3
#
# `softplus(x) = log(1 + eˣ)`. Written as `max(x, 0) + log(1 + e^(−|x|))` it never
# overflows (`np.logaddexp(0, x)` computes the same). Its VJP multiplies by the logistic
# function, read from the saved input.


# %%
def softplus(x):
    x = as_tensor(x)
    out = np.logaddexp(0.0, x.data)

    def vjp(g):
        return (g / (1.0 + np.exp(-x.data)),)

    return record("softplus", out, (x,), vjp, saves=(x,))


error, g_tape, g_fd = md.check_grad(lambda v: softplus(v).sum(), np.array([-3.0, 0.0, 0.5, 4.0]))
print(f"softplus: tape {g_tape}, relative error to finite differences {error:.1e}")
assert error < 1e-8
big = md.tensor([800.0], requires_grad=True)
y = softplus(big)
y.sum().backward()
print(f"softplus(800) = {y.data[0]}, gradient {big.grad[0]}")
assert y.data[0] == 800.0 and big.grad[0] == 1.0
