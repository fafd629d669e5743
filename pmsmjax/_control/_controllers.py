"""PI current and speed controllers and the state and output of field-oriented control
(see `pmsmjax._control._foc` for the control laws)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._plant._params import PMSMParams
from .._validate import check_positive
from ._limits import _limited_pi
from ._saturated import current_control_map
from ._startup import StartupState


class CurrentControllerState(eqx.Module):
    x_I: jnp.ndarray  # integrator state (V, (2,))


class CurrentController(eqx.Module):
    r"""PI current controller with decoupling and anti-windup (see module docstring).

    **Arguments:**

    - `motor`: the controller's machine model (`PMSMParams`; may differ from the plant).
      With a magnetic model (`motor.magnetic`, a static decision) the gain is
      $\alpha_c L_{inc}(i)$ and the decoupling $\omega J\psi(i)$ from the map at the
      measured current (`pmsmjax._control._saturated`); otherwise the constants.
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

    def gains(self, i_dq):
        r"""The PI gains at the current `i_dq` (A, (..., 2)): `(K_p, K_i)`, the proportional
        gain matrix $\alpha_c L$ (Ohm, (..., 2, 2)) with $L$ the incremental inductance
        of the magnetic model at `i_dq` (or diag(L_d, L_q)), and $K_i = \alpha_c R_s$
        (Ohm/s)."""
        m = self.motor
        i_dq = jnp.asarray(i_dq)
        if getattr(m, "magnetic", None) is not None:
            L = m.magnetic.incremental_inductance(i_dq)
        else:
            L = jnp.broadcast_to(m.L_dq, i_dq.shape[:-1] + (2, 2))
        return self.alpha_c * L, self.alpha_c * m.R_s

    def step(self, state: CurrentControllerState, i_ref, i, w, T_s):
        """One step: refs `i_ref`, measured `i` (A, controller frame), speed `w` (rad/s).

        Returns `(state, u)` with `u` the limited voltage reference (V, controller frame).
        """
        m = self.motor
        if getattr(m, "magnetic", None) is not None:
            x_I, u_lim = current_control_map(m.magnetic, self.alpha_c, m.R_s, self.u_max,
                                             i_ref, i, state.x_I, w, T_s)
            return CurrentControllerState(x_I=x_I), jnp.stack(u_lim, -1)
        # Per component (d, q), which XLA fuses into plain element-wise loops.
        i_d, i_q = i[..., 0], i[..., 1]
        Kp_d, Kp_q = self.alpha_c * m.L_d, self.alpha_c * m.L_q
        Ki = self.alpha_c * m.R_s
        e_d, e_q = i_ref[..., 0] - i_d, i_ref[..., 1] - i_q
        x_d, x_q = state.x_I[..., 0], state.x_I[..., 1]
        psi_d, psi_q = m.L_d * i_d + m.psi_f, m.L_q * i_q
        u_d = Kp_d * e_d + x_d + w * -psi_q  # PI + decoupling w J psi
        u_q = Kp_q * e_q + x_q + w * psi_d
        x_I, u_lim = _limited_pi((u_d, u_q), (x_d, x_q), (e_d, e_q), (Kp_d, Kp_q), Ki,
                                 self.u_max, T_s)
        return CurrentControllerState(x_I=x_I), jnp.stack(u_lim, -1)


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
