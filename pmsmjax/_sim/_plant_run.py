"""Open-loop plant runs: the plant driven by a recorded voltage sequence (ZOH between
samples), with no sensor, observer or controller in the loop."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._motor import PMSM, PlantInput
from .._plant._params import Drive
from .._validate import is_concrete
from ._integrate import RK4, check_drive_step, integrate


class PlantTrace(eqx.Module):
    """Output of `run_plant`: the plant's response to a recorded voltage sequence.

    - `t` (s), `i_ab` (A, N x 2) sampled at t_k, `theta` (rad, electrical, unwrapped),
      `w_m` (rad/s, electrical), `i_dq` (A), `tau_M` (N m), all at t_k.
    """

    t: jnp.ndarray
    i_ab: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray
    i_dq: jnp.ndarray
    tau_M: jnp.ndarray


def run_plant(drive: Drive, t, u_ab, tau_L=None, *, solver=RK4(), n_substeps: int = 4,
              theta0=0.0, w_m0=0.0, i_dq0=(0.0, 0.0), w_m_imposed=None) -> PlantTrace:
    """Open-loop plant run driven by a recorded voltage sequence (ZOH between samples).

    **Arguments:**

    - `drive`: the `Drive`.
    - `t`: sampling instants (s), uniform spacing, shape (N,).
    - `u_ab`: voltage commanded over [t_k, t_{k+1}) (V, (N, 2)); the machine receives
      it less the inverter's dead-time error (`drive.inverter.u_dt`; none by default).
    - `tau_L`: load torque over [t_k, t_{k+1}) (N m, (N,)); default zero.
    - `theta0`, `w_m0`, `i_dq0`: initial state (rad, rad/s, A).
    - `w_m_imposed`: if given ((N,) rad/s), the speed is imposed (dynamometer).

    **Returns:** a `PlantTrace` with the state sampled at every t_k (before u_k acts).
    """
    t = jnp.asarray(t)
    u_ab = jnp.asarray(u_ab)
    N = t.shape[0]
    if N < 2:
        raise ValueError(f"`t` needs at least 2 samples; got {N}.")
    if u_ab.shape != (N, 2):
        raise ValueError(f"`u_ab` must have shape (N, 2) = ({N}, 2); got {u_ab.shape}.")
    if is_concrete(t):
        tn = np.asarray(t, dtype=float)
        dt = np.diff(tn)
        if not np.all(np.isfinite(tn)):
            raise ValueError("`t` (s) must be finite; it contains NaN or inf.")
        if dt[0] <= 0 or np.any(np.abs(dt - dt[0]) > 1e-6 * abs(dt[0])):
            raise ValueError(
                "`t` (s) must be increasing and uniformly spaced (relative tolerance 1e-6); "
                f"spacings range from {dt.min():.6g} to {dt.max():.6g} s.")
        check_drive_step(drive, float(dt[0]), solver, n_substeps)
    return _run_plant(drive, t, u_ab, tau_L, solver=solver, n_substeps=n_substeps,
                      theta0=theta0, w_m0=w_m0, i_dq0=i_dq0, w_m_imposed=w_m_imposed)


@eqx.filter_jit
def _run_plant(drive: Drive, t, u_ab, tau_L=None, *, solver, n_substeps, theta0, w_m0,
               i_dq0, w_m_imposed) -> PlantTrace:
    N = t.shape[0]
    T_s = t[1] - t[0]
    tau = jnp.zeros(N) if tau_L is None else jnp.asarray(tau_L)
    plant = PMSM(drive.motor, drive.mechanics, drive.inverter)
    y0 = plant.init(theta0=theta0, w_m0=w_m0, i_dq0=i_dq0)
    imposed = w_m_imposed is not None
    w_imp = jnp.zeros(N) if w_m_imposed is None else jnp.asarray(w_m_imposed)

    def step(y, x):
        u, tl, wi = x
        if imposed:
            y = eqx.tree_at(lambda s: s.w_m, y, wi)
        out = (plant.i_ab(y), y.theta, y.w_m, y.i_dq, plant.torque(y))
        args = PlantInput(u_ab=u, tau_L=tl, free=0.0 if imposed else 1.0)
        return integrate(plant.vector_field, y, args, T_s, solver=solver,
                         n_substeps=n_substeps), out

    _, (i_ab, theta, w_m, i_dq, tau_M) = jax.lax.scan(step, y0, (u_ab, tau, w_imp))
    return PlantTrace(t=t, i_ab=i_ab, theta=theta, w_m=w_m, i_dq=i_dq, tau_M=tau_M)
