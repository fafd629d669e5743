r"""Control on a saturated machine: the current references, the current controller's gains
and decoupling, and field weakening from the controller model's magnetic model.

A controller whose machine model (`CurrentController.motor`, a `PMSMParams`) carries a
magnetic model (`motor.magnetic`, e.g. a `FluxMap`) uses it instead of the constants
`L_d`, `L_q`, `psi_f` (a static decision: with `magnetic=None` nothing here runs and the
constant-inductance laws are unchanged, bit for bit):

- torque $\tau = k_\tau(\psi_d i_q - \psi_q i_d)$ with $\psi = $ `magnetic.flux_dq(i)`;
- `"id_const"`: the q-current of the torque at the fixed d-current, by Newton steps on
  the map's torque from the constants' guess (`NEWTON_STEPS`);
- `"mtpa"`: an `MTPATable` precomputed at construction (the maximum-torque-per-ampere
  current at 2 x 128 current magnitudes, both torque signs, found by a vectorised search
  over the current angle), linearly interpolated in the torque inside the step, then one
  Newton step on the q-current makes the torque exact. A table costs one interpolation
  and one map evaluation per step; Newton steps on the MTPA condition inside the step
  would need the map's second derivatives and a 2 x 2 solve per iteration, several
  times that, for the same answer;
- `"mtpa_fw"`: above, and where the steady-state flux $|\psi(i)|$ exceeds
  $\psi_{max} = u_{margin} u_{max}/|\omega|$ the current vector turns on its own circle
  (same amplitude) towards negative $i_d$ until $|\psi(i)| = \psi_{max}$ (bisection on
  the map). The torque there is below the reference; a speed loop raises the amplitude
  (up to `i_max`) until the load is met;
- current control: $K_p = \alpha_c L_{inc}(i)$ (a 2 x 2 matrix, the incremental
  inductance at the measured current), decoupling $\omega J \psi(i)$ with the map's flux,
  both from one evaluation of the map.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._plant._magnetic import AbstractMagneticModel, solve2
from .._validate import check_positive


#: Newton steps on the map's torque for the q-current at a fixed d-current ("id_const").
#: From the constants' guess (up to 8 % off in torque on the `"ipm3k5_sat"` map) two steps
#: leave below 4e-7 of the rated torque up to the rated torque (tests/test_saturated_control.py).
NEWTON_STEPS = 2


def map_torque(magnetic: AbstractMagneticModel, k_tau, i_d, i_q):
    r"""Torque $k_\tau(\psi_d i_q - \psi_q i_d)$ (N m) and its derivatives with respect to
    `i_d` and `i_q` (N m/A) at the current (A) from the magnetic model's flux."""
    psi_d, psi_q, l_dd, l_dq, l_qd, l_qq = magnetic.flux_and_inductance(i_d, i_q)
    tau = k_tau * (psi_d * i_q - psi_q * i_d)
    return (tau, k_tau * (l_dd * i_q - l_qd * i_d - psi_q),
            k_tau * (l_dq * i_q + psi_d - l_qq * i_d))


def q_current_for_torque(tau_ref, i_d, motor, k_tau, i_q0=None, steps=NEWTON_STEPS):
    """The q-current (A) at which the map's torque at d-current `i_d` (A) is `tau_ref`
    (N m): `steps` Newton steps from `i_q0` (A; default the constants' answer)."""
    i_q = tau_ref / (k_tau * motor.extended_flux(i_d)) if i_q0 is None else i_q0
    for _ in range(steps):
        tau, _, dtau = map_torque(motor.magnetic, k_tau, i_d, i_q)
        i_q = i_q - (tau - tau_ref) / dtau
    return i_q


class MTPATable(eqx.Module):
    r"""Maximum torque per ampere of a magnetic model, tabulated over the torque.

    Rows of increasing torque `tau` (N m) with the MTPA currents `i_d`, `i_q` (A): the
    current of least amplitude for each torque, from the largest negative torque at
    `i_max` through zero to the largest positive one. Build it with `MTPATable.from_model`;
    `CurrentRefs` interpolates it (`FOC.from_drive` builds it for a saturated controller
    model with the `"mtpa"` and `"mtpa_fw"` strategies).
    """

    tau: jax.Array
    i_d: jax.Array
    i_q: jax.Array

    @classmethod
    def from_model(cls, magnetic: AbstractMagneticModel, k_tau, i_max, n: int = 128,
                   n_angle: int = 64) -> MTPATable:
        r"""Tabulate the MTPA of `magnetic` at `n` current amplitudes in (0, `i_max`] (A)
        per torque sign (`k_tau`: torque factor 1.5 n_p, N m per A V s).

        For each amplitude $I$ the current is $I(-\sin\gamma, \pm\cos\gamma)$ with the
        angle advance $\gamma \in [0, \pi/2)$; the torque is evaluated on `n_angle` angles
        at once, the best one's neighbours bracket a golden-section search (60
        iterations, vectorised over the amplitudes), and a final step to the vertex of
        a parabola through three close angles with the map live gives the derivatives
        of the implicit function (the table is differentiable in the map). One compiled
        program per map shape."""
        check_positive("MTPATable.from_model", "i_max", i_max, "A")
        if int(n) < 2 or int(n_angle) < 4:
            raise ValueError(f"`MTPATable.from_model(n=..., n_angle=...)` must be >= 2 and "
                             f">= 4; got n={n!r}, n_angle={n_angle!r}.")
        tau, i_d, i_q = _mtpa_table(magnetic, jnp.asarray(k_tau, float),
                                    jnp.asarray(i_max, float), int(n), int(n_angle))
        table = cls(tau=tau, i_d=i_d, i_q=i_q)
        if not isinstance(table.tau, jax.core.Tracer) and not bool(
                jnp.all(jnp.diff(table.tau) > 0)):
            raise ValueError("`MTPATable.from_model(magnetic=...)`: the MTPA torque does "
                             "not increase with the current amplitude; the magnetic model "
                             "is not that of a motor over (0, i_max].")
        return table

    def currents(self, tau_ref, magnetic: AbstractMagneticModel, k_tau):
        """MTPA currents `(i_d, i_q)` (A) for the torque `tau_ref` (N m): the table
        interpolated linearly in the torque (held at its ends beyond them), then one
        Newton step on `i_q` on the map's torque."""
        tau = jnp.asarray(tau_ref)
        dt = jnp.result_type(tau, self.tau)
        x = self.tau.astype(dt)
        i_d = jnp.interp(tau, x, self.i_d.astype(dt))
        i_q = jnp.interp(tau, x, self.i_q.astype(dt))
        t, _, dtau = map_torque(magnetic, k_tau, i_d, i_q)
        return i_d, i_q - (t - tau) / dtau


@eqx.filter_jit
def _mtpa_table(magnetic, k_tau, i_max, n: int, n_angle: int):
    """`(tau, i_d, i_q)` of `MTPATable.from_model`, compiled as one program."""
    amp = jnp.asarray(i_max) * jnp.arange(1, n + 1) / n
    amp = jnp.concatenate([amp, amp])  # positive, then negative torque
    sign = jnp.concatenate([jnp.ones(n), -jnp.ones(n)]).astype(amp.dtype)
    top = 0.5 * math.pi * (1.0 - 1e-3)

    def t_of(g, a=amp, s=sign, mag=magnetic):  # s * torque at angle advance g
        i_d, i_q = -a * jnp.sin(g), s * a * jnp.cos(g)
        psi_d, psi_q, *_ = mag.flux_and_inductance(i_d, i_q)
        return s * k_tau * (psi_d * i_q - psi_q * i_d)

    grid = jnp.linspace(0.0, top, int(n_angle))
    coarse = jax.vmap(lambda g: t_of(g + 0.0 * amp))(grid)  # (n_angle, 2n)
    j = jnp.argmax(coarse, axis=0)
    h = grid[1] - grid[0]
    lo = jax.lax.stop_gradient(jnp.maximum(grid[j] - h, 0.0))
    hi = jax.lax.stop_gradient(jnp.minimum(grid[j] + h, top))
    r = (math.sqrt(5.0) - 1.0) / 2.0

    def golden(_, ab):
        a, b = ab
        c, d = b - r * (b - a), a + r * (b - a)
        left = jax.lax.stop_gradient(t_of(c) >= t_of(d))
        return jnp.where(left, a, c), jnp.where(left, d, b)

    a, b = jax.lax.fori_loop(0, 60, golden, (lo, hi))
    g = jax.lax.stop_gradient(0.5 * (a + b))
    # one step to the vertex of the parabola through g - h, g, g + h, with the map live:
    # it moves g by rounding only, and its derivative is the implicit function's to O(h^2)
    h = 1e-4
    t_m, t_0, t_p = t_of(g - h), t_of(g), t_of(g + h)
    curv = t_m - 2.0 * t_0 + t_p
    inner = (g > h) & (jax.lax.stop_gradient(curv) < 0)  # g = 0: no saliency, stay
    g = g + jnp.where(inner, 0.5 * h * (t_m - t_p) / jnp.where(inner, curv, -1.0), 0.0)
    i_d, i_q = -amp * jnp.sin(g), sign * amp * jnp.cos(g)
    tau = sign * t_of(g)
    zero = jnp.zeros(1, amp.dtype)

    def join(x):  # negative branch reversed, zero, positive branch
        return jnp.concatenate([x[n:][::-1], zero, x[:n]])

    return join(tau), join(i_d), join(i_q)


def _safe_sqrt(x):
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def field_weakening_map(i_dq, magnetic: AbstractMagneticModel, w, u_lim, steps: int = 40):
    r"""Voltage-limited current references (A) from references `i_dq` (A, e.g. MTPA) on a
    saturated machine: kept where the steady-state flux $|\psi(i)|$ of the map is at most
    $\psi_{max} = $ `u_lim` / |`w`| (`u_lim` usable voltage amplitude, V; `w` electrical
    speed, rad/s), otherwise turned on the circle of their own amplitude $I$ to the largest
    $i_d$ with $|\psi(i_d, \pm\sqrt{I^2 - i_d^2})| \le \psi_{max}$ (bisection over
    $[-I, i_d]$, `steps` iterations, then one Newton step with the speed live for the
    derivatives). Where even $i = (-I, 0)$ exceeds the limit, that is the reference."""
    psi_max = u_lim / jnp.maximum(jnp.abs(w), 1e-9)
    i_d0, i_q0 = i_dq[..., 0], i_dq[..., 1]
    psi = magnetic.flux_dq(i_dq)
    inside = psi[..., 0] ** 2 + psi[..., 1] ** 2 <= psi_max ** 2
    amp2 = jax.lax.stop_gradient(i_d0 ** 2 + i_q0 ** 2)
    s = jnp.where(i_q0 < 0, -1.0, 1.0).astype(i_d0.dtype)

    def excess(i_d, pm):  # |psi|^2 - psi_max^2 on the circle
        p_d, p_q, *_ = magnetic.flux_and_inductance(i_d, s * _safe_sqrt(amp2 - i_d ** 2))
        return p_d ** 2 + p_q ** 2 - pm ** 2

    pm = jax.lax.stop_gradient(psi_max)
    lo = -jnp.sqrt(amp2)
    hi = jax.lax.stop_gradient(jnp.maximum(i_d0, lo))

    def bisect(_, ab):
        a, b = ab
        m = 0.5 * (a + b)
        ok = excess(m, pm) <= 0
        return jnp.where(ok, m, a), jnp.where(ok, b, m)

    a, _ = jax.lax.fori_loop(0, steps, bisect, (lo, hi))
    f, df = jax.jvp(lambda x: excess(x, psi_max), (a,), (jnp.ones_like(a),))
    on = (a > lo) & (jnp.abs(df) > 0)
    i_d = a - jnp.where(on, f / jnp.where(df != 0, df, 1.0), 0.0)
    i_q = s * _safe_sqrt(amp2 - i_d ** 2)
    return jnp.where(inside[..., None], i_dq, jnp.stack([i_d, i_q], -1))


def current_control_map(magnetic, alpha_c, R_s, u_max, i_ref, i, x_I, w, T_s):
    r"""The saturated current controller's step (see the module docstring): returns
    `(x_I, (u_d, u_q))`, the integrators (V, stacked) and the limited voltage (V).

    $u = \alpha_c L_{inc}(i) e + x_I + \omega J\psi(i)$, limited to the circle `u_max`,
    with back-calculation anti-windup through $K_p^{-1} = L_{inc}^{-1}/\alpha_c$."""
    from ._limits import _limit_scale

    i_d, i_q = i[..., 0], i[..., 1]
    psi_d, psi_q, l_dd, l_dq, l_qd, l_qq = magnetic.flux_and_inductance(i_d, i_q)
    e_d, e_q = i_ref[..., 0] - i_d, i_ref[..., 1] - i_q
    x_d, x_q = x_I[..., 0], x_I[..., 1]
    u_d = alpha_c * (l_dd * e_d + l_dq * e_q) + x_d - w * psi_q
    u_q = alpha_c * (l_qd * e_d + l_qq * e_q) + x_q + w * psi_d
    scale = _limit_scale(u_d * u_d + u_q * u_q, u_max)
    v_d, v_q = u_d * scale, u_q * scale
    c_d, c_q = solve2(l_dd, l_dq, l_qd, l_qq, v_d - u_d, v_q - u_q)
    Ki = alpha_c * R_s
    x = jnp.stack([x_d + T_s * Ki * (e_d + c_d / alpha_c),
                   x_q + T_s * Ki * (e_q + c_q / alpha_c)], -1)
    return x, (v_d, v_q)
