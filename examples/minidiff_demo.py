"""A first look at minidiff: differentiate a small function, check it, and optimise with Adam.

Run: python examples/minidiff_demo.py
"""

import numpy as np

import minidiff as md


def lambert(light_position, normals, points, albedo):
    """Lambert shading of a few surface points under a point light of intensity 100."""
    to_light = light_position - points
    r2 = md.dot(to_light, to_light)
    cos_theta = md.maximum(md.dot(normals, md.normalize(to_light)), 0.0)
    return albedo / np.pi * 100.0 * cos_theta / r2


def main() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, size=(64, 3)) * np.array([1, 0, 1])
    normals = np.tile([0.0, 1.0, 0.0], (64, 1))
    true_light = np.array([0.5, 3.0, -0.5])
    target = lambert(true_light, normals, points, 0.7)

    def loss(light):
        diff = lambert(light, normals, points, 0.7) - target
        return (diff * diff).mean()

    start = np.array([-1.0, 2.0, 1.0])
    rel, g_ad, g_fd = md.check_grad(loss, start)
    print(f"gradient at the start: AD {g_ad}, finite differences {g_fd}, rel. error {rel:.1e}")

    light = md.tensor(start, requires_grad=True)
    opt = md.optim.Adam([light], lr=0.05)
    for it in range(301):
        opt.zero_grad()
        value = loss(light)
        value.backward()
        opt.step()
        if it % 50 == 0:
            print(f"iter {it:3d}  loss {value.item():.3e}  light {np.round(light.data, 4)}")
    print(f"true light {true_light}, recovered {np.round(light.data, 4)}")


if __name__ == "__main__":
    main()
