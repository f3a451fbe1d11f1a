"""The paper's Figure 1: the teapot rendered from three viewpoints, written as PNGs.

Run: python examples/render_teapot.py [--size 512] [--out out]
"""

import time

from script_support import command_line

import render

# (camera position, look-at point): the reference view, a view from the left, a high view.
VIEWPOINTS = {
    "front": ((3.0, 2.0, 5.0), (0.0, 0.0, 0.0)),
    "side": ((-4.0, 2.5, 3.5), (0.0, 0.2, 0.0)),
    "top": ((1.0, 5.5, 2.5), (0.0, 0.0, 0.0)),
}


def main(argv=None) -> None:
    args = command_line(__doc__.splitlines()[0], default_iters=None, argv=argv, iterative=False)
    for name, (position, look_at) in VIEWPOINTS.items():
        scene = render.paper_scene(
            width=args.size, height=args.size, camera_position=position, look_at=look_at
        )
        start = time.perf_counter()
        image = render.render(scene)
        seconds = time.perf_counter() - start
        path = render.save_image(image, args.out / "render_teapot" / f"teapot_{name}.png")
        note = ", includes loading the compiled kernels" if name == "front" else ""
        print(f"{name:5s}: {path}  ({seconds * 1e3:.0f} ms{note})")


if __name__ == "__main__":
    main()
