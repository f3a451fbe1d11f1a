"""Random numbers that depend on nothing but (seed, path, dimension).

A Monte Carlo renderer whose random numbers came from a generator's running state would
give a different image on a different number of threads, or when its samples were split
into batches. Here every number is a hash of three integers: the seed, the path's id
(``pixel * spp + sample``, the same in every batch) and the dimension (which decision of
the path it drives, ``DIMENSIONS_PER_BOUNCE`` per bounce). The same seed gives the same
image bit for bit however the work is split, and a replay of a batch of samples (the
adjoint pass of ``render.path.integrator``) draws exactly the numbers of the primal pass.

The hash is SplitMix64's finaliser (Steele, Lea and Flood 2014), applied three times to
fold in the three integers; its outputs pass BigCrush, far more than a renderer needs.
"""

from __future__ import annotations

import numpy as np

from minidiff.threads import jit, job_count, kernel, run_jobs, share

#: Dimensions 0 and 1 place the camera ray in its pixel; bounce k (k = 1, 2, ...) uses
#: dimensions ``2 + DIMENSIONS_PER_BOUNCE * (k - 1) + j`` (``BOUNCE_DIMENSIONS``).
DIMENSIONS_PER_BOUNCE = 8
#: The meaning of j inside a bounce's block of dimensions.
BOUNCE_DIMENSIONS = {
    "lobe": 0,  # diffuse, glossy or mirror
    "direction": 1,  # and 2: the sampled direction
    "roulette": 3,
    "emitter": 4,  # which emissive primitive next-event estimation picks
    "emitter_point": 5,  # and 6: where on it
}

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)


# The hash is discrete work, written once for Numba: the kernels that trace whole paths
# (``render.path.twin.kernel``) call these two, and ``uniform`` runs them over arrays. Plain
# calls, which LLVM inlines: inlined by Numba, each of a kernel's many calls was a copy that
# Numba typed and lowered again (the path kernel's cold compile was slower, its speed the
# same).
@jit(cache=True)
def mix(z):
    """SplitMix64's step on a uint64 (wrapping arithmetic, as intended)."""
    z = z + _GOLDEN
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@jit(cache=True)
def uniform_of(key, dimension):
    """The random number of one path for one ``dimension``, given its key =
    mix(mix(seed) ^ path id): 53 random bits as a float64 in [0, 1)."""
    z = mix(key ^ np.uint64(dimension))
    return np.float64(z >> _S11) * (1.0 / 9007199254740992.0)


@kernel
def _uniforms(job, n_jobs, seed, paths, dimension, out):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``uniform``: its share
    of the paths."""
    seed_key = mix(np.uint64(seed))
    first, stop = share(job, n_jobs, paths.shape[0])
    for i in range(first, stop):
        out[i] = uniform_of(mix(seed_key ^ np.uint64(paths[i])), dimension)


def uniform(seed: int, paths: np.ndarray, dimension: int) -> np.ndarray:
    """(n,) float64 in [0, 1): the random number of each path id in ``paths`` (n,) for one
    ``dimension``, under ``seed``. 53 random bits each (the float64 mantissa)."""
    paths = np.ascontiguousarray(paths, np.uint64)
    out = np.empty(len(paths))
    run_jobs(_uniforms, job_count(len(paths), 65536), np.uint64(seed), paths,
             np.uint64(dimension), out)  # fmt: skip
    return out


def bounce_dimension(bounce: int, name: str) -> int:
    """The dimension of decision ``name`` (see ``BOUNCE_DIMENSIONS``) at bounce k >= 1."""
    return 2 + DIMENSIONS_PER_BOUNCE * (bounce - 1) + BOUNCE_DIMENSIONS[name]


def check_seed(seed, name: str = "seed") -> int:
    """A seed is an integer in [0, 2**64)."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**64:
        raise ValueError(f"render: {name} must be an integer in [0, 2**64), got {seed!r}")
    return int(seed)
