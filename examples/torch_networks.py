"""Networks trained through the renderer with PyTorch, over the ``render.torch`` bridge
(the experiments of ``neural_field.py`` and ``light_network.py``; not a script):

1. ``train_field_torch``: the neural field of ``render.inverse.networks`` trained in
   PyTorch from the same initial weights: the same arithmetic as
   ``train_field_minidiff``, so the same loss curve up to rounding.
2. ``train_light_network``: a network that outputs a scene parameter. From a target image
   of the paper scene it predicts the light's position; it is trained only through the
   renderer (the loss compares the render with the predicted light against the target
   image), over random light positions rendered on the fly.
"""

from __future__ import annotations

import time

import numpy as np

from render.inverse.networks import FieldSetup, field_texture, held_out_psnr, mlp
from render.scene.teapot import paper_scene


def train_field_torch(
    setup: FieldSetup, weights: list[np.ndarray], iters: int = 300, lr: float = 0.01
) -> dict:
    """The same training in PyTorch: the network and Adam are PyTorch's; the renderer is
    called through ``render.torch`` with the views' texture as its one parameter."""
    import torch  # an optional extra: imported where it is used

    import render.torch as rtorch

    params = [torch.tensor(w, dtype=torch.float64, requires_grad=True) for w in weights]
    opt = torch.optim.Adam(params, lr=lr)
    f = rtorch.function(setup.views, ["objects[0].material.texture"])
    features = torch.from_numpy(setup.features)
    targets = torch.from_numpy(setup.targets)
    losses, seconds = [], []
    for it in range(iters + 1):
        start = time.perf_counter()
        opt.zero_grad()
        texture = mlp(params, features, ops=torch).reshape(setup.atlas_shape)
        loss = ((f(texture) - targets) ** 2).mean()
        losses.append(loss.item())
        if it < iters:
            loss.backward()
            opt.step()
        seconds.append(time.perf_counter() - start)
    final = [p.detach().numpy().copy() for p in params]
    return {
        "loss": losses, "seconds": seconds, "weights": final,
        "held_out_psnr": held_out_psnr(setup, field_texture(setup, final)),
    }  # fmt: skip


# -- a network that predicts the light ------------------------------------------------


#: Where the light network's light positions are drawn: uniformly in this box around the
#: paper's light (2, 5, 3).
LIGHT_BOX = (np.array([0.5, 3.5, 1.5]), np.array([3.5, 6.5, 4.5]))


def train_light_network(
    size: int = 32,
    iters: int = 400,
    batch: int = 8,
    hidden: int = 64,
    lr: float = 2e-3,
    held_out: int = 50,
    refine: int = 30,
    refine_lr: float = 0.05,
    seed: int = 0,
) -> dict:
    """Train a PyTorch MLP that maps an image of the paper scene (``size`` square) to the
    light's position, through the renderer only: each step draws ``batch`` light positions
    in ``LIGHT_BOX``, renders their targets (no tape), predicts a position from each
    target, renders the predictions through ``render.torch`` and takes the image MSE. No
    position label is ever used in the loss.

    On ``held_out`` new targets it reports the distance from the predicted to the true
    position, then after ``refine`` Adam steps (``refine_lr``) on each prediction through
    the renderer (the network's guess as the start of an inverse-rendering fit), and the
    same refinement started from the box centre instead, for comparison. Returns those
    errors, the loss curve, the number of renders and the time."""
    import torch

    import render.torch as rtorch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    scene = paper_scene(size, size)
    f = rtorch.function(scene, ["lights[0].position"])
    low, high = (torch.from_numpy(b) for b in LIGHT_BOX)
    centre, half = (low + high) / 2, (high - low) / 2
    net = torch.nn.Sequential(
        torch.nn.Flatten(start_dim=-3),
        torch.nn.Linear(size * size * 3, hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, 3),
    ).double()
    opt = torch.optim.Adam(net.parameters(), lr=lr)

    def predict(images: torch.Tensor) -> torch.Tensor:
        return centre + half * torch.tanh(net(images))  # inside the box by construction

    def targets(positions: np.ndarray) -> torch.Tensor:
        return torch.stack([f(torch.from_numpy(p)) for p in positions]).detach()

    test_positions = rng.uniform(*LIGHT_BOX, (held_out, 3))
    test_images = targets(test_positions)
    renders, losses = held_out, []
    start = time.perf_counter()
    for _ in range(iters):
        positions = rng.uniform(*LIGHT_BOX, (batch, 3))
        images = targets(positions)
        loss = ((f(predict(images)) - images) ** 2).mean()  # f loops over the batch
        opt.zero_grad()
        loss.backward()
        opt.step()
        renders += 2 * batch
        losses.append(loss.item())
    seconds = time.perf_counter() - start
    with torch.no_grad():
        guess = predict(test_images).numpy()

    def refined(start_positions: np.ndarray) -> np.ndarray:
        """``refine`` Adam steps on every held-out light at once (a batch of positions)."""
        positions = torch.tensor(start_positions, requires_grad=True)
        fit = torch.optim.Adam([positions], lr=refine_lr)
        for _ in range(refine):
            fit.zero_grad()
            ((f(positions) - test_images) ** 2).mean(dim=(1, 2, 3)).sum().backward()
            fit.step()
        return positions.detach().numpy()

    def distances(positions: np.ndarray) -> np.ndarray:
        return np.linalg.norm(positions - test_positions, axis=1)

    start_refine = time.perf_counter()
    from_network = refined(guess)
    refine_seconds = time.perf_counter() - start_refine
    from_centre = refined(np.broadcast_to(centre.numpy(), test_positions.shape).copy())
    return {
        "loss": losses, "held_out_error": distances(guess),
        "centre_error": distances(np.broadcast_to(centre.numpy(), test_positions.shape)),
        "refined_error": distances(from_network), "refined_from_centre_error":
        distances(from_centre), "renders": renders, "refine_renders": refine * held_out,
        "refine_steps": refine,
        "seconds": seconds, "refine_seconds": refine_seconds, "predicted": guess,
        "true": test_positions, "parameters": sum(p.numel() for p in net.parameters()),
    }  # fmt: skip
