# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 1 — A tape from scratch, then minidiff's
#
# Reverse-mode automatic differentiation computes the gradient of one scalar output with
# respect to all inputs at the cost of a small multiple of one evaluation. It needs three
# things:
#
# 1. **A record of the computation** (the *tape*, or graph): every intermediate value `v`
#    remembers its parents and how to push a gradient back to them.
# 2. **The chain rule in adjoint form.** Write `v̄ = ∂f/∂v` (the *adjoint* of `v`). If `v`
#    is used by the operations that produce `w1, w2, ...`, then
#
#        v̄ = Σ_k  w̄_k · ∂w_k/∂v .
#
#    Each operation contributes `w̄ · ∂w/∂v` to each of its parents and the contributions add
#    up.
# 3. **An order**: a value's adjoint is complete only once every user of it has contributed.
#    Processing the values in the reverse of a topological order (every value after its
#    parents) guarantees that.
#
# This lesson writes those three things in about thirty lines for Python floats, checks them
# against finite differences, then finds each of them in `minidiff`.

# %%
import math

import numpy as np
from course import figures_folder, save_and_show

import minidiff as md
from minidiff.tensor import as_tensor, record
from render.inverse.plot import line_figure

# This lesson's figures go to out/lessons/01_tape/ (or under $LESSONS_OUT).
OUT = figures_folder("01_tape")

# %% [markdown]
# ## A scalar tape in thirty lines
#
# A `Value` holds `data`, `grad` (its adjoint, accumulated), its `parents`, and a
# `_backward` closure that adds `grad · ∂self/∂parent` to each parent's `grad`. Each
# operation computes its value and its local derivatives `∂self/∂parent` together, while
# the inputs are at hand: the forward value and the derivative sit side by side.


# %%
class Value:
    def __init__(self, data, parents=(), local_grads=()):
        self.data, self.grad, self.parents = float(data), 0.0, parents

        def _backward():  # the chain rule: add grad · ∂self/∂parent to each parent
            for parent, local in zip(parents, local_grads, strict=True):
                parent.grad += self.grad * local

        self._backward = _backward

    def __add__(self, other):  # ∂(a + b)/∂a = 1, ∂(a + b)/∂b = 1
        other = other if isinstance(other, Value) else Value(other)
        return Value(self.data + other.data, (self, other), (1.0, 1.0))

    def __mul__(self, other):  # ∂(ab)/∂a = b, ∂(ab)/∂b = a
        other = other if isinstance(other, Value) else Value(other)
        return Value(self.data * other.data, (self, other), (other.data, self.data))

    __radd__, __rmul__ = __add__, __mul__

    def sin(self):
        return Value(math.sin(self.data), (self,), (math.cos(self.data),))

    def exp(self):
        e = math.exp(self.data)
        return Value(e, (self,), (e,))

    def topological_order(self):  # every value after its parents, each value once
        order, seen = [], set()

        def visit(v):  # depth first: a value is appended after all its parents
            if id(v) not in seen:
                seen.add(id(v))
                for p in v.parents:
                    visit(p)
                order.append(v)

        visit(self)
        return order

    def backward(self):
        self.grad = 1.0  # df/df
        for v in reversed(self.topological_order()):  # every user before the values it uses
            v._backward()


# %% [markdown]
# Our test function uses `x` three times, so its adjoint collects three contributions:
#
#     f(x, y) = x·y + sin(x)·exp(y) + x,        ∂f/∂x = y + cos(x)·exp(y) + 1,
#                                              ∂f/∂y = x + sin(x)·exp(y).


# %%
def f(x, y):
    return x * y + x.sin() * y.exp() + x


x, y = Value(0.5), Value(-1.2)
out = f(x, y)
out.backward()
f_value, grad_x, grad_y = out.data, x.grad, y.grad
exact_x = -1.2 + math.cos(0.5) * math.exp(-1.2) + 1.0
exact_y = 0.5 + math.sin(0.5) * math.exp(-1.2)
print(f"f = {f_value:.6f}   df/dx = {grad_x:.6f}   df/dy = {grad_y:.6f}")
print(f"by hand:          df/dx = {exact_x:.6f}   df/dy = {exact_y:.6f}")

# %% [markdown]
# At `(x, y) = (0.5, −1.2)` the tape gives f = `0.044400` <!-- check: f_value -->,
# ∂f/∂x = `0.064323` <!-- check: grad_x --> and ∂f/∂y = `0.644400` <!-- check: grad_y -->,
# the values of the hand-derived formulas.
#
# ## Checking against finite differences
#
# The central difference `(f(x + h) − f(x − h)) / 2h` has a truncation error of order
# `h² f'''/6` and a rounding error of order `ε |f| / h` (`ε ≈ 2.2e-16`): too large an `h`
# and the Taylor series bites, too small and cancellation does. The sum is smallest near
# `h ≈ ε^(1/3) ≈ 6e-6`, where it is at most of order `ε^(2/3) ≈ 4e-11`. That is why gradient
# checks use `h` around `1e-5` or `1e-6` in float64 and why they can never be tighter than
# about `1e-10`. The figure `fd_error.png` shows the V shape.

# %%
steps = 10.0 ** -np.arange(1, 14)


def f_float(x, y):
    return f(Value(x), Value(y)).data


errors = [abs((f_float(0.5 + h, -1.2) - f_float(0.5 - h, -1.2)) / (2 * h) - grad_x) for h in steps]
for h, e in zip(steps, errors, strict=True):
    print(f"h = {h:.0e}   |central difference - tape| = {e:.1e}")
figure = line_figure(
    {"|central difference - tape|": (steps, errors)},
    title="Central differences against the tape, df/dx at (0.5, -1.2)",
    xlabel="step h",
    ylabel="error",
    logx=True,
    logy=True,
)
save_and_show(figure, OUT / "fd_error.png")
fd_error_at_1e5 = errors[4]
fd_error_at_1e1 = errors[0]

# %% [markdown]
# With `h = 0.1` the difference is off by `4.4e-4` <!-- check: fd_error_at_1e1 --> (the
# `h²` term: a tenth of `h` gives a hundredth of the error down to `h = 1e-4`); with
# `h = 1e-5` it agrees with the tape to better than `1e-11` <!-- check: fd_error_at_1e5 < -->,
# and below that the error grows again. The tape itself has no step and no truncation: it is
# exact up to the rounding of each operation.
#
# ## The same ideas in minidiff
#
# `minidiff.Tensor` is our `Value` over NumPy arrays. Open `minidiff/tensor.py` and
# `minidiff/primitives.py` next to this lesson:
#
# * A **primitive** (`primitives.py`) computes its output with NumPy and calls
#   `record(name, out, inputs, vjp)`. The `vjp` closure is our `_backward`, but pure: it
#   *returns* one gradient per input instead of adding into the parents. For `exp`:
#   `record("exp", y, (x,), lambda g: (g * y,), saves_output=True)`.
#   The name **VJP** (vector-Jacobian product) says what the closure computes for arrays:
#   `g ↦ gᵀ J`, the output adjoint times the Jacobian, without ever forming `J`.
# * `record` (`tensor.py`) wraps the output in a `Tensor` and, if some input requires a
#   gradient, attaches a `Node` holding the inputs, the VJP and a sequence number `seq`: the
#   position on the tape.
# * `Tensor.backward` collects the nodes the output depends on, sorts them by `seq` (the
#   recording order *is* a topological order: nothing can use a value before it exists),
#   and walks them in reverse, summing the gradients arriving at each tensor. Leaves, the
#   tensors you created with `requires_grad=True`, receive `.grad`.
#
# Here is the same function in minidiff, and the tape it records.

# %%
xt = md.tensor(0.5, requires_grad=True)
yt = md.tensor(-1.2, requires_grad=True)
ft = xt * yt + md.sin(xt) * md.exp(yt) + xt


def tape_of(t):
    """The nodes t depends on, in recording order (what backward walks, reversed)."""
    nodes, stack = {}, [t.node]
    while stack:
        node = stack.pop()
        if node is not None and node.seq not in nodes:
            nodes[node.seq] = node
            stack.extend(x.node for x in node.inputs)
    return [nodes[s] for s in sorted(nodes)]


tape = tape_of(ft)
for node in tape:
    print(f"seq {node.seq:>6}: {node.name:<9} inputs of shapes {[x.shape for x in node.inputs]}")
tape_length = len(tape)
# One node's VJP by hand: the last node is the final `+ x`; both inputs get the seed.
print("VJP of the last node for the seed 1:", tape[-1].vjp(np.array(1.0)))

ft.backward()
md_vs_scalar = max(abs(xt.grad - grad_x), abs(yt.grad - grad_y))
print(f"minidiff: df/dx = {xt.grad:.6f}, df/dy = {yt.grad:.6f}; largest difference to the "
      f"scalar tape {md_vs_scalar:.1e}")  # fmt: skip

# %% [markdown]
# The tape has `6` <!-- check: tape_length --> nodes: `multiply`, `sin`, `exp`, `multiply`,
# `add`, `add`. The gradients equal those of the scalar tape to the last bit
# (difference below `1e-15` <!-- check: md_vs_scalar < -->; here exactly 0): the same chain
# rule, the same operations in the same order.
#
# ## Writing a primitive
#
# A new primitive is a forward computation and a VJP handed to `record`. `saves` names the
# inputs whose values the VJP reads, so that `backward` can refuse to run if they were
# changed in between (see "Versions" in `tensor.py`). `md.check_grad` compares the tape with
# central differences (the relative l2 error of Eq. 3 of the paper).


# %%
def cube(x):
    """x³, elementwise.  d/dx = 3x²."""
    x = as_tensor(x)
    return record("cube", x.data**3, (x,), lambda g: (g * 3.0 * x.data**2,), saves=(x,))


values = np.array([0.3, -1.1, 2.0])
cube_error, g_tape, g_fd = md.check_grad(lambda v: (cube(v) * md.sin(v)).sum(), values)
print("tape:", g_tape, " finite differences:", g_fd, f" relative error {cube_error:.1e}")

# %% [markdown]
# The tape and the finite differences of `Σ x³ sin x` agree to a relative error of
# about 1.3e-10, below `1e-9` <!-- check: cube_error < -->: the floor that finite
# differences allow, not an error of the tape.
#
# ## Exercises
#
# 1. Give `Value` a `tanh` method (`d tanh/dx = 1 − tanh²`) and a power `__pow__` for a
#    constant exponent, and check `g(x) = tanh(x)³ + x²` at `x = 0.7` against a central
#    difference with `h = 1e-5`.
# 2. In `topological_order`, the set `seen` makes each value appear once in `order`. Build
#    `a = x; a = a + a` ten times (so `a = 1024·x`) and show what happens to `x.grad` and to
#    the number of `_backward` calls if `visit` forgets `seen`.
# 3. Write a minidiff primitive `softplus(x) = log(1 + eˣ)` with `record`; its derivative is
#    the logistic function `1 / (1 + e⁻ˣ)`. Check it with `md.check_grad` on
#    `x = [-3, 0, 0.5, 4]`, and make the forward pass safe for `x = 800` (where `eˣ`
#    overflows).
#
# Solutions: `lessons/solutions/01_tape.py`.

# %%
print(f"figures in {OUT}")
