"""Savings at trace and compile time that change no value: loop carries that start
batched under `vmap` and with a tangent under `jax.grad` (`batched_like`), and Python
numbers in parameters passed as traced values (`values_as_arrays`).

`vmap` of a `lax.scan` (or `while_loop`) finds which carries are batched by a fixpoint:
it batches the loop body with the initial carries' batch flags, and again, with the
flags or-ed in, as long as a carry that started unbatched comes out batched. A
closed-loop step with some forty carries, whose batched parameter reaches the last
carry only through a chain of others, takes three or four passes over the body, and a
scan nested in a scan multiplies them. Every pass traces and batches the whole step.

`batched_like(carry, *deps)` returns `carry` unchanged in value, but each of its leaves
comes out of a `select` on a constant false predicate that also takes a scalar drawn
from every numeric leaf of `deps`. Outside `vmap` XLA folds the select away; under
`vmap`, if anything in `deps` is batched, every carry is batched from the start and the
fixpoint ends after one pass. `jax.grad` (JAX's linearisation and JVP of a scan) runs
the same fixpoint on which carries have a nonzero tangent: with a differentiated leaf
in `deps`, every carry has one from the start.

Pass as `deps` what the loop body reads (its parameters and inputs). A carry that would
in the end stay unbatched (it depends on nothing batched) is then batched too, which
costs run time, so this is for loops whose carries all follow the batched parameters,
as a closed-loop simulation's do.

`equinox.filter_jit` bakes every Python number of its arguments into the program: a
drive, controller or observer built from Python floats (every preset, `replace_params`,
`scale_motor`, `make_observer(..., zeta1=0.7)`) compiles a new program for each new
value. `values_as_arrays(tree, dtype)` turns those floats into NumPy arrays of the run's
dtype, which `filter_jit` traces, so a new value runs the compiled program again. A
Python zero stays as it is: the code reads it as "absent" (no dead-time model, no
quantisation, no feed-through term) and compiles a smaller program for it.

A `Drive`'s labels (`name`, `notes`, `T_s`: static strings and the commands' default
period) are part of a program's key but not of its computation: `without_labels(tree)`
resets them, so that drives which differ only in their labels (presets of one
structure, a motor file beside the preset it came from) run one compiled program.

`by_batch(single, many, plain)` is a function with one layout for a single run and
another for a batch, where XLA's CPU code for the two differs: `vmap` alone cannot
choose, since it sees no batch size. Its batching rule (`custom_vmap`) runs `single` on
a batch of one as on no batch, `many` on larger batches; a rule of that kind has no
reverse mode, so its derivatives (forward and reverse) are those of `plain`, which
computes the same values.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


def _numeric(x) -> bool:
    return (isinstance(x, (jax.Array, np.ndarray)) and x.size > 0
            and (jnp.issubdtype(x.dtype, jnp.number) or x.dtype == jnp.bool_))


def batched_like(carry, *deps):
    """`carry` (a pytree) with the same values, batched under `vmap` wherever any numeric
    leaf of `deps` is (module docstring)."""
    leaves = [x for x in jax.tree_util.tree_leaves(deps) if _numeric(x)]
    if not leaves:
        return carry
    probe = sum(jnp.real(jnp.ravel(x)[0]).astype(jnp.float32) for x in leaves)
    never = jnp.zeros((), jnp.bool_)

    def one(x):
        if not _numeric(x):
            return x
        return jax.lax.select(jnp.broadcast_to(never, x.shape),
                              jnp.broadcast_to(probe.astype(x.dtype), x.shape), x)

    return jax.tree_util.tree_map(one, carry)


def without_labels(tree):
    """`tree` with every `Drive` in it stripped of its labels (`name`, `notes`, `T_s`
    at their defaults; module docstring): for the arguments of a jitted function that
    reads none of them."""
    from .._plant._params import Drive  # not at module level: the plant imports this

    labels = {f.name: f.default for f in dataclasses.fields(Drive)
              if f.name in ("name", "notes", "T_s")}

    def one(x):
        if not isinstance(x, Drive) or all(getattr(x, k) == v for k, v in labels.items()):
            return x
        # field by field, not through `Drive(...)`: the values were checked when `x` was
        # made, and may be traced here
        new = object.__new__(Drive)
        for f in dataclasses.fields(Drive):
            object.__setattr__(new, f.name, labels.get(f.name, getattr(x, f.name)))
        return new

    return jax.tree_util.tree_map(one, tree, is_leaf=lambda x: isinstance(x, Drive))


def values_as_arrays(tree, dtype):
    """`tree` with every Python float other than zero as a NumPy array of `dtype`
    (module docstring); ints, bools, zeros and everything else unchanged."""
    def one(x):
        if type(x) is float and x != 0.0:
            return np.asarray(x, dtype)
        return x

    return jax.tree_util.tree_map(one, tree)


def by_batch(single, many, plain):
    """`f(*args)`: `single(*args)` unbatched and on a batch of one under `vmap` (the
    unbatched program); `many(axis_size, in_batched, *args)`, which returns every output
    batched along axis 0, on a larger batch; derivatives those of `plain` (module
    docstring). All three must compute the same values (to round-off)."""
    every = lambda out: jax.tree_util.tree_map(lambda _: True, out)  # noqa: E731

    @jax.custom_batching.custom_vmap
    def batched(*a):
        return single(*a)

    @batched.def_vmap
    def _rule(axis_size, in_batched, *a):
        if axis_size == 1:  # through `batched`, so that an enclosing `vmap` chooses again
            a = jax.tree_util.tree_map(lambda x, b: x[0] if b else x, list(a),
                                       list(in_batched))
            out = batched(*a)
            return jax.tree_util.tree_map(lambda x: x[None], out), every(out)
        out = many(axis_size, in_batched, *a)
        return out, every(out)

    @jax.custom_jvp
    def f(*a):
        return batched(*a)

    @f.defjvp
    def _jvp(primals, tangents):
        return jax.jvp(plain, primals, tangents)

    return f
