"""Section 5.7: recover a point light's position and intensity from a random start.

Run: python examples/light_estimation.py [--size 512] [--iters 500] [--seed 42] [--out out]
     [--antialias none|pairs|boundary]
"""

from script_support import EDGES, run_example

from render.inverse.experiments import run_light_estimation


def main(argv=None) -> dict:
    """The command line of ``render.inverse.experiments.run_light_estimation``."""
    return run_example(run_light_estimation, __doc__.splitlines()[0], 500, argv, extra=EDGES)


if __name__ == "__main__":
    main()
