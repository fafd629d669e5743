r"""Discrete-time field-oriented control: PI current and speed controllers.

Every block is a pure state machine `step(state, ..., T_s) -> (state, output)`; the
output at k is computed from the state at k before the state is advanced. Controllers
work in the *controller frame*: the frame at the angle the observer returns (the true
rotor frame in sensored mode, the estimator frame of zhang2022 otherwise).

Current control (per axis, in the controller frame):
$u = K_p (i_{ref} - i) + x_I + \hat\omega_m J (\hat L i + \hat\psi_f)$,
$K_p = \alpha_c \hat L$, $K_i = \alpha_c \hat R_s$, which cancels the machine's pole and
gives a first-order closed loop of bandwidth $\alpha_c$ (rad/s). The voltage is limited to
the inverter's circle $|u| \le u_{max}$; anti-windup by back-calculation to the
realisable voltage: $x_I \leftarrow x_I + T_s K_i [e + K_p^{-1}(u_{lim} - u)]$.

Speed control on the electrical speed: torque reference
$\tau_{ref} = k_p e_\omega + x_{I,\omega}$ with $k_p = 2\alpha_s J/n_p$,
$k_i = \alpha_s^2 J/n_p$ (critically damped for the rigid rotor $J/n_p\,\dot\omega_m =
\tau$), limited to `tau_max` with the same back-calculation anti-windup.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp

from ._params import Drive, PMSMParams
from ._validate import check_positive


if TYPE_CHECKING:  # _control_dtp imports this module
    from ._control_dtp import DualCurrentControl


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
    """

    strategy: str = eqx.field(static=True)
    i_d: float
    i_max: float
    u_margin: float = 0.9

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
            mtpa = CurrentRefs("mtpa", self.i_d, self.i_max, self.u_margin)
            i_mtpa = mtpa(tau_ref, motor, k_tau)
            return field_weakening(i_mtpa, tau_ref, motor, k_tau, w,
                                   self.u_margin * u_max, self.i_max)
        dL = motor.L_d - motor.L_q
        if self.strategy == "id_const":
            i_d = self.i_d + 0.0 * tau_ref
            i_q = tau_ref / (k_tau * (motor.psi_f + dL * i_d))
        else:
            # Newton on tau(i_q) = k i_q (psi_f + dL i_d(i_q)) along the MTPA locus; a fixed
            # number of iterations keeps it differentiable and vmappable.
            i_q = tau_ref / (k_tau * motor.psi_f)
            for _ in range(4):
                i_d = mtpa_i_d(i_q, motor)
                s = jnp.sqrt(motor.psi_f ** 2 + 4.0 * dL ** 2 * i_q ** 2)
                did = 4.0 * dL * i_q / (motor.psi_f + s) - \
                    2.0 * dL * i_q ** 2 * (4.0 * dL ** 2 * i_q / s) / (motor.psi_f + s) ** 2
                f = k_tau * i_q * (motor.psi_f + dL * i_d) - tau_ref
                df = k_tau * (motor.psi_f + dL * i_d + dL * i_q * did)
                i_q = i_q - f / df
            i_d = mtpa_i_d(i_q, motor)
        i_q_max = jnp.sqrt(jnp.maximum(self.i_max ** 2 - i_d ** 2, 0.0))
        i_q = jnp.clip(i_q, -i_q_max, i_q_max)
        return jnp.stack([i_d, i_q], -1)


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
    dL = motor.L_d - motor.L_q
    psi_max = u_lim / jnp.maximum(jnp.abs(w), 1e-9)
    i_d0, i_q0 = i_dq[..., 0], i_dq[..., 1]
    tau = jnp.abs(tau_ref)

    def q_avail(i_d, psi_max):
        q_v = _safe_sqrt(psi_max ** 2 - (motor.L_d * i_d + motor.psi_f) ** 2) / motor.L_q
        return jnp.minimum(q_v, _safe_sqrt(i_max ** 2 - i_d ** 2))

    def torque(i_d, psi_max):
        return k_tau * (motor.psi_f + dL * i_d) * q_avail(i_d, psi_max)

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
    i_q = jnp.clip(tau_ref / (k_tau * (motor.psi_f + dL * i_d)), -q_lim, q_lim)
    return jnp.where(inside[..., None], i_dq, jnp.stack([i_d, i_q], -1))


class CurrentControllerState(eqx.Module):
    x_I: jnp.ndarray  # integrator state (V, (2,))


class CurrentController(eqx.Module):
    """PI current controller with decoupling and anti-windup (see module docstring).

    **Arguments:**

    - `motor`: the controller's machine model (`PMSMParams`; may differ from the plant).
    - `alpha_c`: closed-loop current bandwidth (rad/s), > 0.
    - `u_max`: voltage-vector limit (V, peak phase), > 0.
    """

    motor: PMSMParams
    alpha_c: float
    u_max: float

    def __check_init__(self):
        check_positive("CurrentController", "alpha_c", self.alpha_c, "rad/s")
        check_positive("CurrentController", "u_max", self.u_max, "V")

    def init(self) -> CurrentControllerState:
        return CurrentControllerState(x_I=jnp.zeros(2))

    def step(self, state: CurrentControllerState, i_ref, i, w, T_s):
        """One step: refs `i_ref`, measured `i` (A, controller frame), speed `w` (rad/s).

        Returns `(state, u)` with `u` the limited voltage reference (V, controller frame).
        """
        # Per component (d, q), which XLA fuses into plain element-wise loops.
        m = self.motor
        i_d, i_q = i[..., 0], i[..., 1]
        Kp_d, Kp_q = self.alpha_c * m.L_d, self.alpha_c * m.L_q
        Ki = self.alpha_c * m.R_s
        e_d, e_q = i_ref[..., 0] - i_d, i_ref[..., 1] - i_q
        x_d, x_q = state.x_I[..., 0], state.x_I[..., 1]
        psi_d, psi_q = m.L_d * i_d + m.psi_f, m.L_q * i_q
        u_d = Kp_d * e_d + x_d + w * -psi_q  # PI + decoupling w J psi
        u_q = Kp_q * e_q + x_q + w * psi_d
        scale = _limit_scale(u_d * u_d + u_q * u_q, self.u_max)
        u_d_lim, u_q_lim = u_d * scale, u_q * scale
        x_I = jnp.stack([x_d + T_s * Ki * (e_d + (u_d_lim - u_d) / Kp_d),
                         x_q + T_s * Ki * (e_q + (u_q_lim - u_q) / Kp_q)], -1)
        return CurrentControllerState(x_I=x_I), jnp.stack([u_d_lim, u_q_lim], -1)


class SpeedControllerState(eqx.Module):
    x_I: jnp.ndarray  # integrator (N m)


class SpeedController(eqx.Module):
    """PI speed controller on the electrical speed; output torque reference (N m).

    **Arguments:**

    - `J_over_np`: inertia divided by pole pairs (kg m^2), > 0 (controller's model).
    - `alpha_s`: speed-loop bandwidth (rad/s), > 0.
    - `tau_max`: torque limit (N m), > 0.
    """

    J_over_np: float
    alpha_s: float
    tau_max: float

    def __check_init__(self):
        check_positive("SpeedController", "J_over_np", self.J_over_np, "kg m^2")
        check_positive("SpeedController", "alpha_s", self.alpha_s, "rad/s")
        check_positive("SpeedController", "tau_max", self.tau_max, "N m")

    def init(self) -> SpeedControllerState:
        return SpeedControllerState(x_I=jnp.zeros(()))

    def step(self, state: SpeedControllerState, w_ref, w, T_s):
        kp = 2.0 * self.alpha_s * self.J_over_np
        ki = self.alpha_s ** 2 * self.J_over_np
        e = w_ref - w
        tau = kp * e + state.x_I
        tau_lim = jnp.clip(tau, -self.tau_max, self.tau_max)
        x_I = state.x_I + T_s * ki * (e + (tau_lim - tau) / kp)
        return SpeedControllerState(x_I=x_I), tau_lim


class StartupState(eqx.Module):
    """State of `IfStartup`: the open-loop frame's angle `theta` (rad, wrapped) and speed
    `w` (rad/s, electrical), the handover progress `lam` (0: open loop, 1: the observer's
    frame) and, from the last step, `off` = wrap(open-loop angle - controller angle)
    (rad) and `off_obs` = wrap(open-loop angle - observer angle) (rad); `t`: time since
    the start (s)."""

    theta: jnp.ndarray
    w: jnp.ndarray
    lam: jnp.ndarray
    off: jnp.ndarray
    off_obs: jnp.ndarray
    t: jnp.ndarray


def _wrap(x):
    return jnp.arctan2(jnp.sin(x), jnp.cos(x))


class IfStartup(eqx.Module):
    r"""Open-loop current-vector (I/f) start-up with a smooth handover to the observer.

    A drive's start-up practice, not part of any of the papers: a back-EMF or flux
    observer cannot see the rotor angle at standstill, so the drive first aligns the
    rotor and then turns a current vector of fixed amplitude open loop. *Alignment:* for
    `t_align` the open-loop frame stands still (at the observer's initial angle) and the
    current's amplitude rises smoothly from 0 to $i_{start}$, so that the rotor turns
    to the current vector without a violent swing (applied at once from an unknown angle
    it throws a light rotor around). Then the controller frame is an open-loop frame
    whose speed $\omega_{if}$ follows the speed reference, rate limited to `a_max`;
    the current controller holds $i = (0, \pm i_{start})$ in it (the sign of
    $\omega_{if}$), so the rotor is pulled along with a load angle below 90 deg as long
    as $i_{start}$ makes more torque than the load and the acceleration need. Once
    $|\omega_{if}| \ge$ `w_hand` and the observer agrees with the open-loop frame (its
    angle within 90 deg of it, as the rotor's is, and its speed within 25 %: no false
    lock at $\tilde\theta = \pi$, no slipping PLL) the handover weight $\lambda$ rises
    linearly to 1 over `t_blend` and never falls again (one start per run; until the
    observer agrees the drive stays in open loop); with the smooth step
    $s = \lambda^2(3 - 2\lambda)$ the controller angle is
    $	heta_c = 	heta_{if} + s\,\mathrm{wrap}(\hat	heta - 	heta_{if})$, its speed
    $(1 - s)\omega_{if} + s\hat\omega$, and the current reference
    $(1 - s)\,i_{if} + s\,i_{speed}$, the speed loop's (fed with the controller speed).
    Bumpless: until the handover starts, the speed loop's integrator is held at the
    torque that the open-loop current makes in the observer's frame, so that the speed
    loop takes over from the torque being produced. (The blend turns the shorter way
    from the open-loop angle to the observer's, which rotate together; were they half
    a turn apart at the handover, the direction would be arbitrary.)

    Pure and scan friendly; every branch is a `jnp.where`/clip, so a run stays
    differentiable (almost everywhere) in the parameters. Only speed-controlled runs
    use it (current-controlled runs keep the observer's frame).

    **Arguments:**

    - `i_start`: current-vector amplitude of the open-loop start (A), > 0.
    - `a_max`: rate limit of the open-loop frequency (rad/s^2, electrical), > 0.
    - `w_hand`: speed at which the handover starts (rad/s, electrical), > 0: above the
      observer's low-speed limit.
    - `t_blend`: duration of the handover (s), > 0.
    - `t_align`: duration of the alignment (s), > 0.
    """

    i_start: float
    a_max: float
    w_hand: float
    t_blend: float
    t_align: float = 0.1

    def __check_init__(self):
        check_positive("IfStartup", "i_start", self.i_start, "A")
        check_positive("IfStartup", "a_max", self.a_max, "rad/s^2")
        check_positive("IfStartup", "w_hand", self.w_hand, "rad/s")
        check_positive("IfStartup", "t_blend", self.t_blend, "s")
        check_positive("IfStartup", "t_align", self.t_align, "s")

    @classmethod
    def from_drive(cls, drive: Drive, *, i_start_pu: float = 0.5, w_hand_pu: float = 0.1,
                   a_max_pu: float = 2.0, t_blend: float = 0.05,
                   t_align: float = 0.1) -> IfStartup:
        """The default start: `i_start = i_start_pu * i_max`, handover at
        `w_hand_pu * w_rated`, frequency ramp at most `a_max_pu * w_rated` per second,
        handover over `t_blend` s, after an alignment of `t_align` s."""
        w = float(drive.w_rated)
        return cls(i_start=i_start_pu * float(drive.i_max), a_max=a_max_pu * w,
                   w_hand=w_hand_pu * w, t_blend=t_blend, t_align=t_align)

    def init(self, theta0=0.0) -> StartupState:
        z = jnp.zeros(())
        return StartupState(theta=_wrap(jnp.asarray(theta0, float)), w=z, lam=z, off=z,
                            off_obs=z, t=z)

    def amplitude(self, state: StartupState):
        """The open-loop current amplitude (A): a smooth rise over `t_align`."""
        x = jnp.clip(state.t / self.t_align, 0.0, 1.0)
        return self.i_start * x * x * (3.0 - 2.0 * x)

    def weight(self, state: StartupState):
        """The smooth handover weight $s$ (0: open loop, 1: observer)."""
        lam = state.lam
        return lam * lam * (3.0 - 2.0 * lam)

    def frame(self, state: StartupState, theta_hat, w_hat, w_ref, T_s):
        """Advance the open-loop frame to t_k and return `(state, theta_c, w_c)`: the
        controller frame's angle (rad) and speed (rad/s) at t_k."""
        t = state.t + T_s
        aligning = t < self.t_align
        dw = jnp.clip(w_ref - state.w, -self.a_max * T_s, self.a_max * T_s)
        w_if = jnp.where(aligning, 0.0, state.w + dw)
        th_if = _wrap(state.theta + T_s * w_if)
        # hand over once above w_hand with the observer in agreement: its angle within
        # 90 deg of the open-loop frame (the rotor's load angle is) and its speed within
        # 25 % of the frame's (no false lock at pi, no slipping PLL)
        agree = (jnp.cos(theta_hat - th_if) > 0.0) & (
            jnp.abs(w_hat - w_if) < 0.25 * jnp.abs(w_if))
        go = (state.lam > 0) | ((jnp.abs(w_if) >= self.w_hand) & agree)
        lam = jnp.clip(state.lam + jnp.where(go, T_s / self.t_blend, 0.0), 0.0, 1.0)
        new = StartupState(theta=th_if, w=w_if, lam=lam, off=state.off,
                           off_obs=_wrap(th_if - theta_hat), t=t)
        s = self.weight(new)
        d = _wrap(theta_hat - th_if)
        theta_c = _wrap(th_if + s * d)
        new = eqx.tree_at(lambda t: t.off, new, -s * d)
        return new, theta_c, (1.0 - s) * w_if + s * w_hat


class FOCState(eqx.Module):
    current: CurrentControllerState
    speed: SpeedControllerState
    dual: object = None  # state of `FOC.dual` (dual three-phase control), if any
    startup: StartupState | None = None  # state of `FOC.startup`, if any


class FOCOutput(eqx.Module):
    """What the controller computed at one instant (controller frame)."""

    u_dq: jnp.ndarray       # voltage reference after limiting (V)
    i_ref: jnp.ndarray      # current references (A)
    tau_ref: jnp.ndarray    # torque reference (N m)


class FOC(eqx.Module):
    """Cascaded speed and current control in the controller frame.

    **Arguments:**

    - `current`: `CurrentController`.
    - `speed`: `SpeedController`.
    - `refs`: `CurrentRefs` (torque -> current references).
    - `k_tau`: torque factor of the controller's model (1.5 n_p or 3 n_p).
    - `angle_advance`: if `True`, the voltage is transformed to the stationary frame at
      `theta_hat + (0.5 + d) w_hat T_s` (d = 1 with computational delay) to compensate the
      rotation during the hold interval(s).
    - `dual`: `DualCurrentControl` for a dual three-phase machine: VSD control with the
      x-y currents regulated, or two individual sets (default None: alpha-beta control
      only, zero x-y voltage).
    - `startup`: `IfStartup`, an open-loop I/f start with a handover to the observer
      (speed-controlled runs; default None: the observer's frame from the first
      sample).

    Use `FOC.from_drive(drive, ...)` for the usual bandwidth-based design.
    """

    current: CurrentController
    speed: SpeedController
    refs: CurrentRefs
    k_tau: float
    angle_advance: bool = eqx.field(static=True, default=True)
    dual: DualCurrentControl | None = None
    startup: IfStartup | None = None

    @classmethod
    def from_drive(cls, drive: Drive, *, alpha_c: float = 2 * math.pi * 500.0,
                   alpha_s: float = 2 * math.pi * 5.0, strategy: str = "id_const",
                   i_d: float = 0.0, tau_max: float | None = None,
                   motor: PMSMParams | None = None, angle_advance: bool = True,
                   dual: str | None = None, alpha_xy: float | None = None,
                   alpha_r: float | None = None, i_xy_ref=(0.0, 0.0),
                   startup: IfStartup | None = None) -> FOC:
        """Design from a `Drive`: bandwidths `alpha_c`, `alpha_s` (rad/s), d-current
        `strategy` ("id_const" with `i_d` in A, or "mtpa"), torque limit `tau_max` (N m;
        default 2x rated torque), controller machine model `motor` (default the drive's).

        Dual three-phase drives: `dual="vsd"` regulates the x-y currents to `i_xy_ref`
        (A, anti-synchronous frame) with bandwidth `alpha_xy` (rad/s, default `alpha_c`)
        and harmonic gain `alpha_r` (rad/s, default `alpha_xy / 10`); `dual="individual"`
        controls the two sets each in its own frame, with the per-set model (self
        inductances $(L_{d,q} + L_{xy})/2$) unless `motor` is given (see
        `pmsmjax.DualCurrentControl`; `alpha_c` also sets the differential mode's
        bandwidth, several times higher).

        `startup`: an `IfStartup` (e.g. `IfStartup.from_drive(drive)`), or None.
        """
        dual_ctrl = None
        if dual is not None:
            from ._control_dtp import DualCurrentControl, XYCurrentController

            if not drive.dual:
                raise ValueError(f"`FOC.from_drive(dual={dual!r})` needs a dual "
                                 f"three-phase drive; {drive.name!r} is three-phase.")
            if dual not in ("vsd", "individual"):
                raise ValueError(f"`FOC.from_drive(dual=...)` must be None, 'vsd' or "
                                 f"'individual'; got {dual!r}.")
            ab, L_xy = drive.motor.ab, drive.motor.L_xy
            if dual == "individual":
                if motor is None:
                    motor = eqx.tree_at(lambda m: (m.L_d, m.L_q), ab,
                                        (0.5 * (ab.L_d + L_xy), 0.5 * (ab.L_q + L_xy)))
                dual_ctrl = DualCurrentControl("individual")
            else:
                a_xy = alpha_c if alpha_xy is None else alpha_xy
                a_r = 0.1 * a_xy if alpha_r is None else alpha_r
                xy = XYCurrentController(L_xy=L_xy, R_s=ab.R_s, alpha_xy=a_xy,
                                         alpha_r=a_r, u_max=drive.inverter.u_lim)
                dual_ctrl = DualCurrentControl("vsd", xy=xy, i_xy_ref=i_xy_ref)
        motor = drive.three_phase_motor if motor is None else motor
        tau_max = 2.0 * drive.tau_rated if tau_max is None else tau_max
        return cls(
            current=CurrentController(motor=motor, alpha_c=alpha_c,
                                      u_max=drive.inverter.u_lim),
            speed=SpeedController(J_over_np=drive.mechanics.J / drive.motor.n_p,
                                  alpha_s=alpha_s, tau_max=tau_max),
            refs=CurrentRefs(strategy=strategy, i_d=i_d, i_max=drive.i_max),
            k_tau=drive.k_tau,
            angle_advance=angle_advance,
            dual=dual_ctrl,
            startup=startup,
        )

    def init(self, theta0=0.0) -> FOCState:
        """The controller state at k = 0 (`theta0`: the start-up's open-loop angle, rad,
        if it has one)."""
        return FOCState(current=self.current.init(), speed=self.speed.init(),
                        dual=None if self.dual is None else self.dual.init(self),
                        startup=None if self.startup is None else
                        self.startup.init(theta0))

    def frame(self, state: FOCState, theta_hat, w_hat, w_ref, T_s):
        """The controller frame at t_k: `(state, theta_c, w_c)` (rad, rad/s): the
        observer's estimate, or `startup`'s frame while it runs."""
        if self.startup is None:
            return state, theta_hat, w_hat
        su, th, w = self.startup.frame(state.startup, theta_hat, w_hat, w_ref, T_s)
        return eqx.tree_at(lambda s: s.startup, state, su), th, w

    def _references(self, state: FOCState, w_hat, w_ref, T_s, i_ref_override,
                    speed_mode):
        """Speed loop and current references: `(speed state, i_ref, tau_ref)`."""
        if speed_mode:
            s_state, tau_ref = self.speed.step(state.speed, w_ref, w_hat, T_s)
            i_ref = self.refs(tau_ref, self.current.motor, self.k_tau, w=w_hat,
                              u_max=self.current.u_max)
        else:
            s_state = state.speed
            i_ref = i_ref_override
            m = self.current.motor
            tau_ref = self.k_tau * (
                (m.psi_f + (m.L_d - m.L_q) * i_ref[..., 0]) * i_ref[..., 1])
        return s_state, i_ref, tau_ref

    def step(self, state: FOCState, i_dq, w_hat, w_ref, T_s, *, i_ref_override=None,
             speed_mode=True):
        """One control step.

        - `i_dq`: measured current in the controller frame (A).
        - `w_hat`: speed used for feedback and decoupling (rad/s, electrical).
        - `w_ref`: speed reference (rad/s, electrical); ignored if `speed_mode` is False.
        - `i_ref_override`: current references (A) used instead of the speed loop when
          `speed_mode` is False (current/torque-controlled operation).
        """
        su = state.startup if self.startup is not None and speed_mode else None
        if su is not None:
            # bumpless handover: before it starts, the speed loop's integrator holds the
            # torque of the open-loop current in the observer's frame
            i_q_if = self.startup.amplitude(su) * jnp.where(su.w < 0, -1.0, 1.0)
            m = self.current.motor
            tau_obs = self.k_tau * m.psi_f * i_q_if * jnp.cos(su.off_obs)
            state = eqx.tree_at(lambda s: s.speed.x_I, state,
                                jnp.where(su.lam > 0, state.speed.x_I,
                                          tau_obs).astype(state.speed.x_I.dtype))
        s_state, i_ref, tau_ref = self._references(state, w_hat, w_ref, T_s,
                                                   i_ref_override, speed_mode)
        if su is not None:
            s = self.startup.weight(su)
            # the open-loop current (0, i_q_if) in the controller frame
            i_if = jnp.stack([-jnp.sin(su.off) * i_q_if, jnp.cos(su.off) * i_q_if])
            i_ref = (1.0 - s) * i_if + s * i_ref
        c_state, u = self.current.step(state.current, i_ref, i_dq, w_hat, T_s)
        return FOCState(current=c_state, speed=s_state, dual=state.dual,
                        startup=state.startup), \
            FOCOutput(u_dq=u, i_ref=i_ref, tau_ref=tau_ref)
