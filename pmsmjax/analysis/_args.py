"""Argument checks and conversions shared by the analysis functions: the observer and the
true machine they are given, an operating point from numbers, and the float values of an
observer or machine as arrays (inputs of a compiled program, not constants in it)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._plant._params import PMSMParams
from ..observers import AbstractObserver, OperatingPoint


def check_observer(owner: str, observer) -> None:
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`{owner}(observer=...)` must be an `AbstractObserver` (e.g. "
                         f"`pj.observers.make_observer('eso', drive)`); got "
                         f"{type(observer).__name__}.")


def check_plant(owner: str, plant) -> None:
    if not isinstance(plant, PMSMParams):
        raise ValueError(f"`{owner}(plant=...)` must be the true machine's `PMSMParams` "
                         f"(e.g. `drive.three_phase_motor`); got {type(plant).__name__}.")


def _op(w_m, i_dq, dtype):
    return OperatingPoint(jnp.asarray(w_m, dtype), jnp.asarray(i_dq, dtype))


def as_arrays(tree, dtype, *, ints: bool = True):
    """Every float/int leaf (Python or NumPy) of `tree` as a JAX array of `dtype`, so that
    jitted functions trace them instead of baking them in (no recompile per value).
    `ints=False` keeps Python ints as they are (an observer's counts and sizes, which its
    code may branch on)."""
    def conv(v):
        if isinstance(v, bool) or (not ints and isinstance(v, int)):
            return v
        if isinstance(v, float | int | np.ndarray | np.generic | jax.Array):
            return jnp.asarray(v, dtype) if jnp.issubdtype(jnp.result_type(v), jnp.floating) \
                or isinstance(v, int | float) else jnp.asarray(v)
        return v
    return jax.tree_util.tree_map(conv, tree)


def _program_inputs(observer, plant, dtype=float):
    """`observer` and `plant` with their float values (design, machine parameters) as
    arrays of `dtype`: inputs of a compiled program, not constants compiled into it, so
    another design or a mismatched model reuses the program (Python ints, an observer's
    counts and sizes, stay as they are)."""
    return as_arrays(observer, dtype, ints=False), as_arrays(plant, dtype, ints=False)

