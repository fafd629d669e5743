"""Integration of the plant over one sampling period with the inputs held (ZOH).

Any diffrax Runge-Kutta solver can be used; the default is the classical fourth-order
method `RK4`, stepped manually `n_substeps` times with a fixed step (no adaptive control,
no while loop), which keeps the closed-loop scan cheap and reverse-mode differentiable.
Other solvers are stepped with diffrax's `solver.step`. `RK4` itself is evaluated as
straight-line code (`_rk4_step`): diffrax runs the stages of any Runge-Kutta method in a
loop with a stage buffer, which XLA cannot fuse and which dominated the cost of a
closed-loop step.
"""

from __future__ import annotations

import math

import diffrax as dfx
import jax
import numpy as np

from .._plant._params import Drive, DualThreePhaseParams
from .._validate import check_positive, is_concrete


_RK4_TABLEAU = dfx.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(dfx.AbstractERK):
    """Classical fourth-order Runge-Kutta method (fixed step; no error estimate)."""

    tableau = _RK4_TABLEAU
    interpolation_cls = dfx.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 4


# Largest h * |lambda| on the negative real axis for which each explicit method is
# stable; used to reject sampling periods the plant cannot be integrated with.
_STABILITY_RADIUS = {
    "Euler": 2.0, "Heun": 2.0, "Midpoint": 2.0, "Ralston": 2.0,
    "Bosh3": 2.51, "RK4": 2.78, "Tsit5": 3.5, "Dopri5": 3.3, "Dopri8": 5.0,
}


def stability_radius(solver) -> float:
    return _STABILITY_RADIUS.get(type(solver).__name__, 2.0)


def _rk4_step(vector_field, t0, h, y0, args):
    """One classical RK4 step of size `h`, the same arithmetic as diffrax's `RK4` stepping
    (increments `k_i = h f_i`, stage values `y0 + a_i k_{i-1}`, weights 1/6, 1/3, 1/3, 1/6).
    """
    tree_map = jax.tree_util.tree_map

    def incr(t, y):
        return tree_map(lambda f: f * h, vector_field(t, y, args))

    k1 = incr(t0, y0)
    k2 = incr(t0 + 0.5 * h, tree_map(lambda y, k: y + 0.5 * k, y0, k1))
    k3 = incr(t0 + 0.5 * h, tree_map(lambda y, k: y + 0.5 * k, y0, k2))
    k4 = incr(t0 + h, tree_map(lambda y, k: y + k, y0, k3))
    return tree_map(
        lambda y, a, b, c, d: y + (a * (1 / 6) + b * (1 / 3) + c * (1 / 3) + d * (1 / 6)),
        y0, k1, k2, k3, k4)


def integrate(vector_field, y0, args, T_s, *, solver, n_substeps: int):
    """Integrate `dy/dt = vector_field(t, y, args)` over [0, T_s] with fixed steps."""
    h = T_s / n_substeps
    if type(solver) is RK4:
        def one(y, k):
            return _rk4_step(vector_field, k * h, h, y, args), None
    else:
        term = dfx.ODETerm(vector_field)
        state = solver.init(term, 0.0, h, y0, args)

        def one(y, k):
            t0 = k * h
            y1, _, _, _, _ = solver.step(term, t0, t0 + h, y, args, state,
                                         made_jump=False)
            return y1, None

    if n_substeps == 1:
        return one(y0, 0)[0]
    # Full unrolling makes compile time grow steeply with n_substeps (16 s at 8); a
    # rolled inner loop costs the same at run time for more than two substeps.
    y, _ = jax.lax.scan(one, y0, np.arange(n_substeps, dtype=float),
                        unroll=n_substeps if n_substeps <= 2 else 1)
    return y


def check_step(T_s, n_substeps, rate, solver) -> None:
    """Reject a step `T_s / n_substeps` (s) outside the solver's stability region.

    `rate` is an upper bound of the plant's fastest eigenvalue magnitude (1/s).
    """
    if not isinstance(n_substeps, int | np.integer) or n_substeps < 1:
        raise ValueError(f"`n_substeps` must be a positive integer; got {n_substeps!r}.")
    h = float(T_s) / n_substeps
    r = stability_radius(solver)
    if h * float(rate) >= r:
        need = math.ceil(float(T_s) * float(rate) / r * 1.05)
        raise ValueError(
            f"`T_s={float(T_s):.6g}` s is too long for {type(solver).__name__} with "
            f"n_substeps={n_substeps}: the plant's fastest mode ({float(rate):.4g} 1/s) "
            f"needs T_s/n_substeps < {r / float(rate):.4g} s; use n_substeps >= {need} "
            f"or a shorter T_s."
        )


def plant_rate(motor, w_max) -> float:
    """Upper bound of the magnitude of the plant's electrical eigenvalues (1/s) up to the
    electrical speed `w_max` (rad/s)."""
    p = motor.ab if isinstance(motor, DualThreePhaseParams) else motor
    L_min = min(float(p.L_d), float(p.L_q))
    if isinstance(motor, DualThreePhaseParams):
        L_min = min(L_min, float(motor.L_xy))
    return math.hypot(float(p.R_s) / L_min, float(w_max))


def check_drive_step(drive: Drive, T_s, solver, n_substeps) -> None:
    """The checks every run of the plant makes (`simulate`, `run_plant`, `identify`):
    `drive` is a `Drive`, the sampling period `T_s` (s) is positive, and the solver's step
    `T_s / n_substeps` is stable up to twice the rated speed (`check_step`)."""
    if not isinstance(drive, Drive):
        raise ValueError(f"`drive` must be a `pmsmjax.Drive`; got {type(drive).__name__}.")
    check_positive("simulate", "T_s", T_s, "s")
    if is_concrete((drive.motor, drive.w_rated)):
        check_step(T_s, n_substeps, plant_rate(drive.motor, 2.0 * float(drive.w_rated)),
                   solver)
