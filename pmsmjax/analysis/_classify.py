"""Feasibility of a design at one operating point from the equilibria of its error
dynamics, for any observer: a `DesignClass` (the statuses are those of
`pmsmjax.analysis._feasibility`: 0 feasible, 1 infeasible, 2 no equilibrium, -1
degenerate). `classify` uses the family's closed form where it has one
(`observer.fast_classify`), else the generic equilibria (`equilibria_traced`)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._args import _op, check_observer
from ._generic import equilibria_traced


class DesignClass(eqx.Module):
    """Classification of designs (any batch shape `...`).

    - `status`: 0 feasible, 1 infeasible, 2 no equilibrium at all (mismatch only), -1
      degenerate (see the module docstring).
    - `n_nonzero`: number of equilibria other than the designed one.
    - `stable_theta`: angle of the stable non-designed equilibrium closest to 0 (rad),
      NaN if there is none (the static position error of an infeasible design).
    - `theta`: angles of the non-designed equilibria (rad), `(..., K)`, NaN padded.
    - `stable`: which of them are stable, `(..., K)`.
    - `principal_stable`: the designed equilibrium is stable.
    - `principal_theta`: its angle (rad): 0 with matched parameters, the steady-state
      error caused by the mismatch otherwise (NaN if there is no equilibrium).
    """

    status: jnp.ndarray
    n_nonzero: jnp.ndarray
    stable_theta: jnp.ndarray
    theta: jnp.ndarray
    stable: jnp.ndarray
    principal_stable: jnp.ndarray
    principal_theta: jnp.ndarray


def _class_from_equilibria(eq, degenerate=False) -> DesignClass:
    """Feasibility of one operating point from its equilibria (any observer): status 0
    if no equilibrium other than the principal one is stable, 1 if one is, 2 if there
    is no equilibrium at all, -1 if the analysis is degenerate."""
    other = eq.nonprincipal
    stable = eq.stable & other
    deg = (eq.status == -1) | degenerate
    none = ~deg & (eq.status == 2)
    inf = jnp.any(stable)
    key = jnp.where(stable, jnp.abs(eq.theta), jnp.inf)
    st = eq.theta[jnp.argmin(key)]
    K = eq.valid.shape[-1]
    # move the non-principal equilibria to the front
    order = jnp.argsort(~other, stable=True)[: K - 1]
    theta = jnp.where(other, eq.theta, jnp.nan)[order]
    return DesignClass(
        status=jnp.where(deg, -1, jnp.where(none, 2, jnp.where(inf, 1, 0))).astype(jnp.int32),
        n_nonzero=jnp.where(deg, 0, eq.n_nonzero),
        stable_theta=jnp.where(inf & ~deg, st, jnp.nan),
        theta=jnp.where(deg, jnp.nan, theta),
        stable=stable[order] & ~deg,
        principal_stable=eq.stable[eq.principal] & ~deg,
        principal_theta=jnp.where(deg | none, jnp.nan, eq.theta[eq.principal]))


CLASSIFY_METHODS = ("auto", "closed_form", "generic")


def _resolve_classify(owner, observer, plant, method, w_m, i_dq):
    if method not in CLASSIFY_METHODS:
        raise ValueError(f"`{owner}(method=...)` must be one of "
                         f"{', '.join(map(repr, CLASSIFY_METHODS))}; got {method!r}.")
    fast = plant is None and observer.fast_classify(w_m, i_dq) is not None
    if method == "closed_form" and not fast:
        raise ValueError(
            f"`{owner}(method='closed_form')`: {type(observer).__name__} with this design "
            f"has no closed-form classification" + (" with observer-model mismatch"
                                                     if plant is not None else "")
            + "; use method='generic'.")
    return "closed_form" if (fast and method != "generic") else "generic"


def classify(observer, plant=None, w_m=None, i_dq=(0.0, 0.0), *, method: str = "auto",
             **options) -> DesignClass:
    """Feasibility of `observer` at one operating point (any observer, vmappable).

    **Arguments:**

    - `observer`: any `AbstractObserver`; its `motor` is its model.
    - `plant`: the true machine (`PMSMParams`); None = the observer's own model (matched,
      which allows a closed form where the family has one).
    - `w_m`: electrical speed (rad/s); `i_dq`: current in the estimated frame (A).
    - `method`: `"auto"` (the closed form when it applies, else generic),
      `"closed_form"` or `"generic"` (`equilibria`).
    - `options`: passed to `equilibria` (grid, slots, tolerances).

    Returns a `DesignClass` (status 0 feasible, 1 infeasible, 2 no equilibrium, -1
    degenerate; never raises for a bad point).
    """
    check_observer("classify", observer)
    if w_m is None:
        raise ValueError("`classify(w_m=...)` (rad/s) is required.")
    dtype = jnp.result_type(w_m, float)
    op = _op(w_m, i_dq, dtype)
    if _resolve_classify("classify", observer, plant, method, op.w_m, op.i_dq) == \
            "closed_form":
        return observer.fast_classify(op.w_m, op.i_dq)
    plant = observer.motor if plant is None else plant
    return _class_from_equilibria(equilibria_traced(observer, plant, op, **options))
