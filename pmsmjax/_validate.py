"""Input validation shared by all Modules.

Structural or concrete-value problems raise `ValueError` at construction and name the
argument, its value and the allowed range. Values that are JAX tracers (inside `jit` or
`vmap`) cannot be inspected in Python; they are checked where they are used with
`eqx.error_if` or reported through a run's status instead.
"""

from __future__ import annotations

import math

import jax
import numpy as np


def is_concrete(x) -> bool:
    """True if `x` holds no JAX tracer, so its value can be inspected now."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x))


def _fmt(x) -> str:
    a = np.asarray(x)
    if a.ndim == 0:
        return repr(a.item())
    return np.array2string(a, threshold=6)


def check_finite(owner: str, name: str, value, unit: str = "") -> None:
    if value is None or not is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        u = f" ({unit})" if unit else ""
        raise ValueError(f"`{owner}({name}=...)`{u} must be finite; got {_fmt(value)}.")


def check_positive(owner: str, name: str, value, unit: str = "", allow_zero=False) -> None:
    """Raise `ValueError` unless every element of `value` is finite and > 0 (>= 0)."""
    if value is None or not is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    bad = ~np.isfinite(a) | ((a < 0) if allow_zero else (a <= 0))
    if np.any(bad):
        rel = ">= 0" if allow_zero else "> 0"
        u = f" ({unit})" if unit else ""
        raise ValueError(
            f"`{owner}({name}=...)`{u} must be finite and {rel}; got {_fmt(value)}."
        )


def check_range(owner: str, name: str, value, lo=-math.inf, hi=math.inf, unit: str = "",
                lo_open=False, hi_open=False) -> None:
    if value is None or not is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    bad = ~np.isfinite(a) & ~(np.isinf(a) & (np.isinf(lo) | np.isinf(hi)))
    bad |= (a <= lo) if lo_open else (a < lo)
    bad |= (a >= hi) if hi_open else (a > hi)
    if np.any(bad):
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        u = f" ({unit})" if unit else ""
        raise ValueError(
            f"`{owner}({name}=...)`{u} must lie in {lb}{lo}, {hi}{rb}; got {_fmt(value)}."
        )


class NonFiniteInputError(ValueError):
    """A recording or an initial value handed to `replay` or `simulate` holds NaN or inf
    (the message names the argument, and for a recording the first bad sample and its
    time)."""
