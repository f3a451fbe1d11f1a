"""Section 5.6: recover the camera pose (position and look-at point) from a target render.

Run: python examples/camera_calibration.py [--size 512] [--iters 500] [--seed 42] [--out out]
     [--angle 10]
"""

from script_support import run_example

from render.inverse.experiments import run_camera_calibration

ANGLE = {"--angle": {"type": float, "default": 10.0, "help": "initial view error (degrees)"}}


def main(argv=None) -> dict:
    """The command line of ``render.inverse.experiments.run_camera_calibration``."""
    return run_example(run_camera_calibration, __doc__.splitlines()[0], 500, argv, extra=ANGLE)


if __name__ == "__main__":
    main()
