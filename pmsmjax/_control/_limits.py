"""Current references and limits: the voltage circle, MTPA, voltage-limit-aware field
weakening and stumper's d-current feedforward (see `pmsmjax._control._foc` for the
control structure)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._plant._params import PMSMParams
from .._validate import check_positive
from ._saturated import MTPATable, field_weakening_map, q_current_for_torque


def limit_vector(u, u_max):
    """Scale the 2-vector `u` onto the circle of radius `u_max` if it lies outside.

    Differentiable everywhere (the norm is computed with a safe square root).
    """
    scale = _limit_scale(u[..., 0] * u[..., 0] + u[..., 1] * u[..., 1], u_max)
    return u * scale[..., None]


def _limit_scale(n2, u_max):
    """Factor that scales a vector of squared length `n2` onto the circle `u_max`."""
    n = jnp.sqrt(jnp.where(n2 > 0, n2, 1.0))
    return jnp.where(n > u_max, u_max / n, 1.0)


def _limited_pi(u, x, e, Kp, Ki, u_max, T_s):
    r"""Limit the output `u = (u_1, u_2)` of a two-component PI controller onto the circle
    `u_max` and advance its integrators `x = (x_1, x_2)` with back-calculation
    anti-windup, $x \leftarrow x + T_s K_i (e + (u_{lim} - u) / K_p)$.

    **Arguments:**

    - `u`, `x`, `e`: pairs of the unlimited output (V), the integrator states (V) and the
      current errors (A), one entry per component.
    - `Kp`: pair of proportional gains (Ohm); `Ki`: the integral gain (Ohm/s).
    - `u_max`: the voltage limit (V); `T_s`: the sampling period (s).

    Returns `(x_I, u_lim)`: the integrators stacked on the last axis (V) and the pair of
    limited outputs (V).
    """
    scale = _limit_scale(u[0] * u[0] + u[1] * u[1], u_max)
    u_lim = (u[0] * scale, u[1] * scale)
    x_I = jnp.stack([x[k] + T_s * Ki * (e[k] + (u_lim[k] - u[k]) / Kp[k]) for k in (0, 1)],
                    -1)
    return x_I, u_lim


def mtpa_i_d(i_q, motor: PMSMParams):
    r"""d-current on the maximum-torque-per-ampere locus for a given q-current (A).

    Solves $\psi_f i_d + (L_d - L_q)(i_d^2 - i_q^2) = 0$ for the root with $i_d \le 0$
    when $L_d < L_q$, in a form that stays finite as $L_d \to L_q$ (then $i_d = 0$).
    """
    dL = motor.L_d - motor.L_q
    s = jnp.sqrt(motor.psi_f ** 2 + 4.0 * dL ** 2 * i_q ** 2)
    return 2.0 * dL * i_q ** 2 / (motor.psi_f + s)


class CurrentRefs(eqx.Module):
    r"""Torque reference -> current references $(i_d, i_q)$ in the controller frame.

    **Arguments:**

    - `strategy`: `"id_const"` (constant `i_d`), `"mtpa"`, or `"mtpa_fw"`: MTPA below
      the voltage limit and field weakening above it (`field_weakening`; needs the
      speed and the voltage limit, which `FOC.step` passes).
    - `i_d`: the constant d-current reference for `"id_const"` (A).
    - `i_max`: current-vector limit (A); `i_q` is reduced to respect it.
    - `u_margin`: for `"mtpa_fw"`, the fraction of the voltage limit the steady-state
      flux may use (-, default 0.9: headroom for the resistive drop and the current
      controller).
    - `mtpa`: the `MTPATable` of the controller model's magnetic model, needed by
      `"mtpa"` and `"mtpa_fw"` when that model is saturated (`FOC.from_drive` builds it);
      default None.

    With a controller model that carries a magnetic model (`motor.magnetic`, a static
    decision) the references come from the map, not the constants
    (`pmsmjax._control._saturated`): the q-current of the map's torque at the constant
    d-current, the tabulated MTPA, and field weakening on the map's flux.
    """

    strategy: str = eqx.field(static=True)
    i_d: float
    i_max: float
    u_margin: float = 0.9
    mtpa: MTPATable | None = None

    def __check_init__(self):
        if self.strategy not in ("id_const", "mtpa", "mtpa_fw"):
            raise ValueError(
                f"`CurrentRefs(strategy=...)` must be 'id_const', 'mtpa' or 'mtpa_fw'; "
                f"got {self.strategy!r}."
            )
        check_positive("CurrentRefs", "i_max", self.i_max, "A")
        check_positive("CurrentRefs", "u_margin", self.u_margin, "-")

    def __call__(self, tau_ref, motor: PMSMParams, k_tau, w=None, u_max=None):
        """Current references (A) for torque `tau_ref` (N m); `w` (rad/s, electrical)
        and `u_max` (V) are used by `"mtpa_fw"` only."""
        if self.strategy == "mtpa_fw":
            if w is None or u_max is None:
                raise ValueError("`CurrentRefs(strategy='mtpa_fw')` needs the speed `w` "
                                 "(rad/s) and the voltage limit `u_max` (V).")
            mtpa = CurrentRefs("mtpa", self.i_d, self.i_max, self.u_margin, self.mtpa)
            i_mtpa = mtpa(tau_ref, motor, k_tau)
            if getattr(motor, "magnetic", None) is not None:
                return field_weakening_map(i_mtpa, motor.magnetic, w,
                                           self.u_margin * u_max)
            return field_weakening(i_mtpa, tau_ref, motor, k_tau, w,
                                   self.u_margin * u_max, self.i_max)
        if getattr(motor, "magnetic", None) is not None:
            return self._saturated(tau_ref, motor, k_tau)
        dL = motor.L_d - motor.L_q
        if self.strategy == "id_const":
            i_d = self.i_d + 0.0 * tau_ref
            i_q = tau_ref / (k_tau * motor.extended_flux(i_d))
        else:
            # Newton on tau(i_q) = k i_q (psi_f + dL i_d(i_q)) along the MTPA locus; a fixed
            # number of iterations keeps it differentiable and vmappable.
            i_q = tau_ref / (k_tau * motor.psi_f)
            for _ in range(4):
                i_d = mtpa_i_d(i_q, motor)
                s = jnp.sqrt(motor.psi_f ** 2 + 4.0 * dL ** 2 * i_q ** 2)
                did = 4.0 * dL * i_q / (motor.psi_f + s) - \
                    2.0 * dL * i_q ** 2 * (4.0 * dL ** 2 * i_q / s) / (motor.psi_f + s) ** 2
                psi_ex = motor.extended_flux(i_d)
                f = k_tau * i_q * psi_ex - tau_ref
                df = k_tau * (psi_ex + dL * i_q * did)
                i_q = i_q - f / df
            i_d = mtpa_i_d(i_q, motor)
        i_q_max = jnp.sqrt(jnp.maximum(self.i_max ** 2 - i_d ** 2, 0.0))
        i_q = jnp.clip(i_q, -i_q_max, i_q_max)
        return jnp.stack([i_d, i_q], -1)

    def _saturated(self, tau_ref, motor: PMSMParams, k_tau):
        """`"id_const"` and `"mtpa"` on the controller model's magnetic model."""
        if self.strategy == "id_const":
            i_d = self.i_d + 0.0 * tau_ref
            i_q = q_current_for_torque(tau_ref, i_d, motor, k_tau)
        else:
            if self.mtpa is None:
                raise ValueError(
                    f"`CurrentRefs(strategy={self.strategy!r})` on a saturated controller "
                    f"model needs `mtpa=MTPATable.from_model(motor.magnetic, k_tau, i_max)` "
                    f"(`FOC.from_drive` builds it); got mtpa=None.")
            i_d, i_q = self.mtpa.currents(tau_ref, motor.magnetic, k_tau)
        i_q_max = jnp.sqrt(jnp.maximum(self.i_max ** 2 - i_d ** 2, 0.0))
        i_q = jnp.clip(i_q, -i_q_max, i_q_max)
        return jnp.stack([i_d, i_q], -1)


def d_current_feedforward(i_q_ref, dw_ref_dt, v1, i_d0=0.0):
    r"""stumper (48) with the sign corrected: $i_d^* = i_{d0}^* - \tan(\Delta\varphi_e)
    i_q^*$ with the tracking filter's lag $\Delta\varphi_e = \dot\omega^*/v_1$ (39).

    - `i_q_ref`: q current reference (A); `dw_ref_dt`: slope of the *electrical* speed
      reference (rad/s^2, $n_p\dot\omega_M^*$); `v1`: tracking-filter gain (1/s^2);
      `i_d0`: the constant d current (A).

    During an acceleration the estimate lags ($\theta - \tilde\theta = \Delta\varphi_e >
    0$), so a current $i_0$ set in the estimated frame is $e^{-\Delta\varphi_e J}i_0$ in
    the rotor frame: its d component $i_d^*\cos\Delta\varphi_e + i_q^*\sin\Delta\varphi_e$
    vanishes for $i_d^* = -\tan(\Delta\varphi_e)\,i_q^*$, a *negative* d current while
    accelerating with positive torque (as the paper's experiment reports, -2.25 A). The
    printed $+\tan$ doubles the misalignment instead.
    """
    return i_d0 - jnp.tan(dw_ref_dt / v1) * i_q_ref


def _safe_sqrt(x):
    """sqrt(max(x, 0)) with a finite derivative (0) where x <= 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def field_weakening(i_dq, tau_ref, motor: PMSMParams, k_tau, w, u_lim, i_max):
    r"""Voltage-limit-aware current references (A) from references `i_dq` (A, e.g. MTPA).

    In steady state and neglecting the resistance the voltage is $|\omega|\,|\psi|$,
    $\psi = [L_d i_d + \psi_f, L_q i_q]$, so the flux may be at most
    $\psi_{max} = u_{lim}/|\omega|$ (the voltage ellipse). References inside the ellipse
    are kept. Otherwise the d current is lowered along the ellipse: with
    $q(i_d) = \min(\sqrt{\psi_{max}^2 - (L_d i_d + \psi_f)^2}/L_q, \sqrt{i_{max}^2 - i_d^2})$
    the largest |q current| the ellipse and the current circle `i_max` (A) allow, the
    torque available at $i_d$ is $T(i_d) = k_\tau(\psi_f + (L_d - L_q)i_d)\,q(i_d)$; the
    reference is the largest $i_d$ (least weakening) with $T(i_d) = |\tau_{ref}|$, on the
    ellipse, or where `tau_ref` (N m) cannot be reached, the $i_d$ of the largest
    available torque (at least $\max(-\psi_f/L_d, -i_{max})$). The largest torque is found by
    golden-section search and the $i_d$ by bisection (fixed iteration counts: vmappable),
    then one Newton step on $T(i_d) = |\tau_{ref}|$ in which the speed and the torque are
    live, so that the derivatives are the implicit function's (differentiable). `w`
    electrical speed (rad/s), `u_lim` usable voltage amplitude (V).
    """
    psi_max = u_lim / jnp.maximum(jnp.abs(w), 1e-9)
    i_d0, i_q0 = i_dq[..., 0], i_dq[..., 1]
    tau = jnp.abs(tau_ref)

    def q_avail(i_d, psi_max):
        q_v = _safe_sqrt(psi_max ** 2 - (motor.L_d * i_d + motor.psi_f) ** 2) / motor.L_q
        return jnp.minimum(q_v, _safe_sqrt(i_max ** 2 - i_d ** 2))

    def torque(i_d, psi_max):
        return k_tau * motor.extended_flux(i_d) * q_avail(i_d, psi_max)

    inside = jnp.hypot(motor.L_d * i_d0 + motor.psi_f, motor.L_q * i_q0) <= psi_max
    pm = jax.lax.stop_gradient(psi_max)
    ta = jax.lax.stop_gradient(tau)
    lo = jnp.maximum(-motor.psi_f / motor.L_d, -i_max) + 0.0 * ta
    hi = jnp.maximum(jax.lax.stop_gradient(i_d0), lo)
    # the largest available torque in [lo, hi] (golden section, a unimodal T)
    r = (math.sqrt(5.0) - 1.0) / 2.0

    def golden(_, ab):
        a, b = ab
        c, d = b - r * (b - a), a + r * (b - a)
        left = torque(c, pm) >= torque(d, pm)
        return jnp.where(left, a, c), jnp.where(left, d, b)

    a, b = jax.lax.fori_loop(0, 50, golden, (lo, hi))
    peak = 0.5 * (a + b)
    peak = jnp.where(torque(peak, pm) > 0, peak, lo)  # nothing available: weaken fully
    reachable = torque(peak, pm) >= ta

    # the largest i_d in [peak, hi] with T = |tau_ref| inside the ellipse (T decreases)
    def bisect(_, ab):
        a, b = ab
        m = 0.5 * (a + b)
        ok = (torque(m, pm) >= ta) & (motor.L_d * m + motor.psi_f <= pm)  # on the ellipse
        return jnp.where(ok, m, a), jnp.where(ok, b, m)

    a, _ = jax.lax.fori_loop(0, 60, bisect, (peak, hi))
    i_d = jnp.where(reachable, a, peak)
    # one Newton step with the speed and torque live: exact value, implicit derivatives
    t, dt = jax.jvp(lambda x: torque(x, psi_max), (i_d,), (jnp.ones_like(i_d),))
    step = jnp.where(reachable & (jnp.abs(dt) > 0), (t - tau) / jnp.where(dt != 0, dt, 1.0),
                     0.0)
    i_d = i_d - step
    q_lim = q_avail(i_d, psi_max)
    i_q = jnp.clip(tau_ref / (k_tau * motor.extended_flux(i_d)), -q_lim, q_lim)
    return jnp.where(inside[..., None], i_dq, jnp.stack([i_d, i_q], -1))
