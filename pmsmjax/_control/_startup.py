"""Open-loop I/f start-up with a handover to the observer's frame."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import wrap_angle
from .._plant._params import Drive
from .._validate import check_positive


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
        return StartupState(theta=wrap_angle(jnp.asarray(theta0, float)), w=z, lam=z, off=z,
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
        th_if = wrap_angle(state.theta + T_s * w_if)
        # hand over once above w_hand with the observer in agreement: its angle within
        # 90 deg of the open-loop frame (the rotor's load angle is) and its speed within
        # 25 % of the frame's (no false lock at pi, no slipping PLL)
        agree = (jnp.cos(theta_hat - th_if) > 0.0) & (
            jnp.abs(w_hat - w_if) < 0.25 * jnp.abs(w_if))
        go = (state.lam > 0) | ((jnp.abs(w_if) >= self.w_hand) & agree)
        lam = jnp.clip(state.lam + jnp.where(go, T_s / self.t_blend, 0.0), 0.0, 1.0)
        new = StartupState(theta=th_if, w=w_if, lam=lam, off=state.off,
                           off_obs=wrap_angle(th_if - theta_hat), t=t)
        s = self.weight(new)
        d = wrap_angle(theta_hat - th_if)
        theta_c = wrap_angle(th_if + s * d)
        new = eqx.tree_at(lambda t: t.off, new, -s * d)
        return new, theta_c, (1.0 - s) * w_if + s * w_hat
