"""Section 5.7: recover a point light's position and intensity from a random start.

Run: python examples/light_estimation.py [--size 512] [--iters 500] [--seed 42] [--out out]
"""

import json

from minidiff.memory import keep_freed_memory
from render.experiments import command_line, run_light_estimation


def main(argv=None) -> None:
    # Opt-in allocator tuning: keep freed arrays for reuse instead of page-faulting them
    # back in every iteration (the README's benchmarks measure how much; minidiff/memory.py).
    keep_freed_memory()
    args = command_line(__doc__.splitlines()[0], default_iters=500, argv=argv)
    result = run_light_estimation(
        size=args.size, iters=args.iters, seed=args.seed, out=args.out, quiet=args.quiet
    )
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
