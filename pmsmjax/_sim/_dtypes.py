"""Floating-point dtypes of a run: the dtype a run takes from its parameters, and casts of
a PyTree's floating-point leaves to it (`astype` is the public one)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def run_dtype(*trees):
    """Floating dtype of a run: the result type of the floating-point leaves of `trees`
    (Python floats are weak: float32 parameters give a float32 run, see `astype`)."""
    leaves = [x for x in jax.tree_util.tree_leaves(trees)
              if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return jnp.result_type(float, *leaves)


def cast_floats(tree, dtype):
    """`tree` with every leaf as a JAX array, the floating-point ones cast to `dtype`."""
    def cast(x):
        x = jnp.asarray(x)
        return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x

    return jax.tree_util.tree_map(cast, tree)


def astype(tree, dtype):
    """Cast every floating-point array leaf of `tree` to `dtype` (e.g. jnp.float32)."""
    def cast(x):
        if isinstance(x, jax.Array | float) and jnp.issubdtype(jnp.result_type(x), jnp.floating):
            return jnp.asarray(x, dtype)
        return x

    return jax.tree_util.tree_map(cast, tree)
