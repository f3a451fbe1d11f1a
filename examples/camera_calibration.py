"""Section 5.6: recover the camera pose (position and look-at point) from a target render.

Run: python examples/camera_calibration.py [--size 512] [--iters 500] [--seed 42] [--out out]
     [--angle 10] [--antialias none|pairs|boundary] [--search 0]

--search N spends N low-resolution renders on a greedy search of the camera before the
gradients (``render.inverse.basin.greedy_search``; counted in the time reported).
"""

from script_support import EDGES, run_example

from render.inverse.experiments import run_camera_calibration

EXTRA = {
    "--angle": {"type": float, "default": 10.0, "help": "initial view error (degrees)"},
    "--search": {"type": int, "default": 0, "help": "renders of a search stage first"},
    **EDGES,
}


def main(argv=None) -> dict:
    """The command line of ``render.inverse.experiments.run_camera_calibration``."""
    return run_example(run_camera_calibration, __doc__.splitlines()[0], 500, argv, extra=EXTRA)


if __name__ == "__main__":
    main()
