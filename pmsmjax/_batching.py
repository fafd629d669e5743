"""Loop carries that start batched under `vmap`, and with a tangent under `jax.grad` (a
trace-time saving, no change of value).

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
"""

from __future__ import annotations

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
