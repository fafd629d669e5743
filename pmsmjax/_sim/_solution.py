"""Results of simulations: the status enumeration and the `Trajectory` Module."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


class RESULTS(eqx.Enumeration):
    """Per-run status of a simulation."""

    successful = ""
    diverged = (
        "The simulation diverged: a state became non-finite or left the physical bounds "
        "(|i| > 20 i_max, |w_m| or the observer's speed estimate |w_hat| > 20 "
        "w_rated). The state was frozen at the last good "
        "sample. Pass `throw=False` to inspect `Trajectory.status` per run."
    )


class Trajectory(eqx.Module):
    """Samples of one closed-loop run (every `save_every`-th sampling instant).

    All arrays have a leading time axis (plus any batch axes added by `vmap` in front).

    - `t`: sampling instants t_k (s).
    - `theta`, `w_m`: true electrical angle (rad, wrapped to (-pi, pi]) and speed (rad/s).
    - `theta_hat`, `w_hat`: observer estimates at t_k (rad, rad/s).
    - `theta_err`: `wrap(theta - theta_hat)` (rad), true minus estimate.
    - `i_dq`: true current in rotor coordinates (A); `i_ab` in the stationary frame (A).
    - `i_meas_ab`: the current the controller saw (noise, quantisation, delay) (A).
    - `u_ab`: voltage commanded over [t_k, t_{k+1}) (V, stationary frame); the machine
      receives it less the inverter's dead-time error when `drive.inverter.u_dt > 0`.
    - `u_dq`: that voltage in rotor coordinates at t_k (V).
    - `i_ref`: current references (A, controller frame); `tau_ref` torque reference.
    - `tau_M`: electromagnetic torque at t_k (N m); `tau_L`: load torque (N m).
    - `w_m_ref`: speed reference (rad/s).
    - `ise_theta`: integral of theta_err^2 over the whole run (rad^2 s).
    - `ise_w`: integral of (w_m_ref - w_m)^2 (rad^2/s); `ise_w_hat`: of (w_m - w_hat)^2.
    - `status`: `RESULTS` code of the run (0 = successful).
    - `t_end` (s), `theta_end` (rad, wrapped), `w_m_end` (rad/s), `i_dq_end` (A): the
      plant state after the last step, at t_N = N T_s (the samples stop at t_{N-1}).
    - `extras`: the observer's own estimates by name (`Estimate.extras`, units in the
      observer class's `extras`), e.g. `psi_ab_hat` (V s) for the zhang2022 observers.
    - `i_xy`, `u_xy`: dual three-phase machines only (else None): the x-y subspace current
      (A) at t_k and voltage (V) applied over [t_k, t_{k+1}), stationary x-y frame.
    """

    t: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray
    theta_hat: jnp.ndarray
    w_hat: jnp.ndarray
    theta_err: jnp.ndarray
    i_dq: jnp.ndarray
    i_ab: jnp.ndarray
    i_meas_ab: jnp.ndarray
    u_ab: jnp.ndarray
    u_dq: jnp.ndarray
    i_ref: jnp.ndarray
    tau_ref: jnp.ndarray
    tau_M: jnp.ndarray
    tau_L: jnp.ndarray
    w_m_ref: jnp.ndarray
    ise_theta: jnp.ndarray
    ise_w: jnp.ndarray
    ise_w_hat: jnp.ndarray
    status: RESULTS
    extras: dict = eqx.field(default_factory=dict)
    t_end: jnp.ndarray | None = None
    theta_end: jnp.ndarray | None = None
    w_m_end: jnp.ndarray | None = None
    i_dq_end: jnp.ndarray | None = None
    i_xy: jnp.ndarray | None = None
    u_xy: jnp.ndarray | None = None

    @property
    def ok(self):
        """Boolean (per run): True where the run finished without divergence."""
        return self.status == RESULTS.successful
