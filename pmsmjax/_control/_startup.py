"""Open-loop I/f start-up with a handover to the observer's frame."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from .._frames import wrap_angle
from .._plant._params import Drive
from .._validate import check_positive


#: The stabiliser's largest d current, as a fraction of the open-loop amplitude (the
#: current vector turned by at most 45 deg).
_ID_MAX = math.sqrt(0.5)


def swing_frequency(drive: Drive, i: float) -> float:
    r"""The angular frequency (rad/s) at which the rotor of `drive` swings about the rest
    point of a current vector of amplitude `i` (A) held in a fixed frame, for small
    swings: $\omega_n = \sqrt{k_\tau \psi_a i\, n_p / J}$ with $k_\tau = 1.5 n_p$ and
    the active flux $\psi_a = \psi_f + (L_d - L_q) i$ (the stiffness of the torque
    $k_\tau(\psi_f + (L_d - L_q) i_d) i_q$ at $i_d = i$, $i_q = 0$); friction left
    out."""
    m = drive.motor
    psi_a = float(m.psi_f) + (float(m.L_d) - float(m.L_q)) * i
    if not psi_a > 0:
        raise ValueError(f"IfStartup: the active flux psi_f + (L_d - L_q) i_start = "
                         f"{psi_a:.4g} V s is not positive at i_start = {i:.4g} A: the "
                         f"current vector makes no restoring torque; lower i_start_pu.")
    return math.sqrt(float(drive.k_tau) * psi_a * i * float(m.n_p)
                     / float(drive.mechanics.J))


class StartupState(eqx.Module):
    """State of `IfStartup`: the open-loop frame's angle `theta` (rad, wrapped) and speed
    `w` (rad/s, electrical), the handover progress `lam` (0: open loop, 1: the observer's
    frame) and, from the last step, `off` = wrap(open-loop angle - controller angle)
    (rad) and `off_obs` = wrap(open-loop angle - observer angle) (rad); `t`: time since
    the start (s); `w_r`: the stabiliser's filtered estimate of the rotor's speed from
    the frame's back-EMF (rad/s, electrical)."""

    theta: jnp.ndarray
    w: jnp.ndarray
    lam: jnp.ndarray
    off: jnp.ndarray
    off_obs: jnp.ndarray
    t: jnp.ndarray
    w_r: jnp.ndarray


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
    $\theta_c = \theta_{if} + s\,\mathrm{wrap}(\hat\theta - \theta_{if})$, its speed
    $(1 - s)\omega_{if} + s\hat\omega$, and the current reference
    $(1 - s)\,i_{if} + s\,i_{speed}$, the speed loop's (fed with the controller speed).
    Bumpless: until the handover starts, the speed loop's integrator is held at the
    torque that the open-loop current makes in the observer's frame, so that the speed
    loop takes over from the torque being produced. (The blend turns the shorter way
    from the open-loop angle to the observer's, which rotate together; were they half
    a turn apart at the handover, the direction would be arbitrary.)

    *Stabiliser* (`c_damp` > 0; `from_drive(..., zeta=0.7)`). A current vector held in an
    open-loop frame pulls the rotor like a spring: the rotor swings about its rest point
    (the frame's d axis, $\delta = \theta - \theta_{if} = \pm\pi/2$) at
    $\omega_n = \sqrt{k_\tau \psi_a |i| n_p / J}$ with nothing to damp it but friction,
    so a rotor that starts far from the rest point (up to half a turn: the angle is
    unknown) is still swinging when the ramp starts and may never be pulled in. The
    stabiliser damps the swing from the frame's d-axis voltage: with the current held at
    $(0, i)$ in the frame, $u_d = R i_d + \partial\psi_d/\partial\delta\,(\omega -
    \omega_{if}) - \omega_{if}\psi_q$ and near the rest point
    $\partial\psi_d/\partial\delta = -\mathrm{sign}(i)\,\psi_a$,
    $\psi_q = \mathrm{sign}(i)(\psi_f + L_d|i|)$, with the active flux
    $\psi_a = \psi_f + (L_d - L_q)|i|$ (derived in `tests/test_startup.py` against the
    machine's flux linkage), so the controller's own voltage gives the rotor's speed
    $\hat\omega$ (low-pass filtered at `w_damp`). A d current in the frame,
    $i_d = c\,(\hat\omega - \omega_{if})\,i$ (the vector turned by at most 45 deg),
    makes the torque of the vector turned by $-c(\hat\omega - \omega_{if})$: the rest
    point's stiffness times $c$ times the rotor's speed, a damping ratio
    $\zeta = c\,\omega_n/2$ (the frame itself stays on its ramp: turning the frame
    instead left an oscillation of 0.2-2.5 deg through the current controller's lag).
    From the handover on the d current is held and fades with the blend. Measured
    (`tests/test_startup.py`, docs/lock-and-startup.md): the swing decays to below 3 %
    within one period on the three single-machine presets, and from 24 initial angle
    errors each the ESO drive fails to start only from the dead point (the rotor exactly
    opposite the rest point, where the current makes no torque). It is not the default:
    on zhang750 under load the rotor then reaches the handover speed before the LESO and
    the AFO have converged, and their handover onto a 40-deg error loses the lock.

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
    - `c_damp`: the stabiliser's gain $c$ (s), >= 0: the current vector's turn (rad)
      per rad/s of the rotor's speed relative to the open-loop frame; 0 turns the
      stabiliser off (a plain I/f start).
    - `w_damp`: bandwidth of the stabiliser's speed estimate (rad/s), > 0 when
      `c_damp` > 0.
    """

    i_start: float
    a_max: float
    w_hand: float
    t_blend: float
    t_align: float = 0.1
    c_damp: float = 0.0
    w_damp: float = 0.0

    def __check_init__(self):
        check_positive("IfStartup", "i_start", self.i_start, "A")
        check_positive("IfStartup", "a_max", self.a_max, "rad/s^2")
        check_positive("IfStartup", "w_hand", self.w_hand, "rad/s")
        check_positive("IfStartup", "t_blend", self.t_blend, "s")
        check_positive("IfStartup", "t_align", self.t_align, "s")
        check_positive("IfStartup", "c_damp", self.c_damp, "s", allow_zero=True)
        if self.c_damp > 0:
            check_positive("IfStartup", "w_damp", self.w_damp, "rad/s (with c_damp > 0)")

    @classmethod
    def from_drive(cls, drive: Drive, *, i_start_pu: float = 0.5, w_hand_pu: float = 0.1,
                   a_max_pu: float = 2.0, t_blend: float = 0.05,
                   t_align: float = 0.1, zeta: float = 0.0) -> IfStartup:
        """The default start: `i_start = i_start_pu * i_max`, handover at
        `w_hand_pu * w_rated`, frequency ramp at most `a_max_pu * w_rated` per second,
        handover over `t_blend` s, after an alignment of `t_align` s, with the
        stabiliser designed for the damping ratio `zeta` of the rotor's swing at
        `i_start` (`swing_frequency`; `c_damp = 2 zeta / omega_n`, the speed estimate
        filtered at `10 omega_n`); the default `zeta=0` starts without it (a plain I/f
        start), and 0.7 is its design value (docs/lock-and-startup.md: what it does on
        each preset)."""
        check_positive("IfStartup.from_drive", "zeta", zeta, "", allow_zero=True)
        w = float(drive.w_rated)
        i_start = i_start_pu * float(drive.i_max)
        if zeta == 0:  # a plain start: no swing frequency needed
            return cls(i_start=i_start, a_max=a_max_pu * w, w_hand=w_hand_pu * w,
                       t_blend=t_blend, t_align=t_align)
        w_n = swing_frequency(drive, i_start)
        return cls(i_start=i_start, a_max=a_max_pu * w, w_hand=w_hand_pu * w,
                   t_blend=t_blend, t_align=t_align, c_damp=2.0 * zeta / w_n,
                   w_damp=10.0 * w_n)

    def init(self, theta0=0.0) -> StartupState:
        z = jnp.zeros(())
        return StartupState(theta=wrap_angle(jnp.asarray(theta0, float)), w=z, lam=z, off=z,
                            off_obs=z, t=z, w_r=z)

    def rotor_speed(self, state: StartupState, u_d, i_d, motor, T_s):
        """The stabiliser's filtered estimate of the rotor's speed (rad/s, electrical)
        after a step whose controller (in the open-loop frame, current about
        (0, +-amplitude)) applied the d-axis voltage `u_d` (V) with the d current `i_d`
        (A) measured, from the controller's constant machine model `motor` (the class
        docstring's relation)."""
        i = self.amplitude(state)
        sign = self.direction(state)
        psi_a = motor.psi_f + (motor.L_d - motor.L_q) * i
        slip = -(sign * (u_d - motor.R_s * i_d)
                 + state.w * (motor.psi_f + motor.L_d * i)) / psi_a
        a = self.w_damp * T_s / (1.0 + self.w_damp * T_s)
        w_r = state.w_r + a * (state.w + slip - state.w_r)
        return jnp.where(state.lam > 0, state.w_r, w_r)  # held from the handover on

    def damping_current(self, state: StartupState):
        """The stabiliser's d current in the open-loop frame (A): the current vector
        turned against the rotor's swing relative to the frame, `c_damp` times the
        rotor's speed relative to it times the signed amplitude (at most 45 deg)."""
        i = self.signed_amplitude(state)
        turn = jnp.clip(self.c_damp * (state.w_r - state.w), -_ID_MAX, _ID_MAX)
        return i * turn

    @staticmethod
    def direction(state: StartupState):
        """The open-loop current's sign: +1, or -1 while the frame turns backwards."""
        return jnp.where(state.w < 0, -1.0, 1.0)

    def signed_amplitude(self, state: StartupState):
        """The open-loop q current in the frame (A): `amplitude` with `direction`."""
        return self.amplitude(state) * self.direction(state)

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
        th_if = wrap_angle(state.theta + T_s * w_if)
        # hand over once above w_hand with the observer in agreement: its angle within
        # 90 deg of the open-loop frame (the rotor's load angle is) and its speed within
        # 25 % of the frame's (no false lock at pi, no slipping PLL)
        agree = (jnp.cos(theta_hat - th_if) > 0.0) & (
            jnp.abs(w_hat - w_if) < 0.25 * jnp.abs(w_if))
        go = (state.lam > 0) | ((jnp.abs(w_if) >= self.w_hand) & agree)
        lam = jnp.clip(state.lam + jnp.where(go, T_s / self.t_blend, 0.0), 0.0, 1.0)
        new = StartupState(theta=th_if, w=w_if, lam=lam, off=state.off,
                           off_obs=wrap_angle(th_if - theta_hat), t=t,
                           # from the handover on the stabiliser's d current is held (and
                           # faded by the blend): its speed moves with the frame's
                           w_r=jnp.where(state.lam > 0, state.w_r + (w_if - state.w),
                                         state.w_r))
        s = self.weight(new)
        d = wrap_angle(theta_hat - th_if)
        theta_c = wrap_angle(th_if + s * d)
        new = eqx.tree_at(lambda t: t.off, new, -s * d)
        return new, theta_c, (1.0 - s) * w_if + s * w_hat
