"""Section 5.8: recover the teapot's albedo from a random colour, projected onto [0, 1]^3.

Run: python examples/material_recovery.py [--size 512] [--iters 100] [--seed 42] [--out out]
     [--antialias none|pairs|boundary]
"""

from script_support import EDGES, run_example

from render.inverse.experiments import run_material_recovery


def main(argv=None) -> dict:
    """The command line of ``render.inverse.experiments.run_material_recovery``."""
    return run_example(run_material_recovery, __doc__.splitlines()[0], 100, argv, extra=EDGES)


if __name__ == "__main__":
    main()
