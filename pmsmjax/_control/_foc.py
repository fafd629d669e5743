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

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp

from .._frames import cos_sin
from .._plant._params import Drive, PMSMParams
from ._controllers import (
    CurrentController,
    FOCOutput,
    FOCState,
    SpeedController,
)
from ._dtp import DualCurrentControl, XYCurrentController
from ._limits import CurrentRefs
from ._saturated import MTPATable, map_torque
from ._startup import IfStartup


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

    On a saturated machine: when the controller's machine model `current.motor` carries
    a magnetic model (`motor.magnetic`, a static decision; `from_drive` keeps the drive's
    unless `use_map=False`), the references come from the map's torque (`CurrentRefs`,
    an `MTPATable` for MTPA), the current controller's gain from the incremental
    inductance at the measured current and its decoupling and the field weakening from
    the map's flux. Otherwise the constants `L_d`, `L_q`, `psi_f`, exactly as without a
    map.
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
                   startup: IfStartup | None = None, use_map: bool = True) -> FOC:
        """Design from a `Drive`: bandwidths `alpha_c`, `alpha_s` (rad/s), d-current
        `strategy` ("id_const" with `i_d` in A, "mtpa" or "mtpa_fw"), torque limit `tau_max` (N m;
        default 2x rated torque), controller machine model `motor` (default the drive's).

        Dual three-phase drives: `dual="vsd"` regulates the x-y currents to `i_xy_ref`
        (A, anti-synchronous frame) with bandwidth `alpha_xy` (rad/s, default `alpha_c`)
        and harmonic gain `alpha_r` (rad/s, default `alpha_xy / 10`); `dual="individual"`
        controls the two sets each in its own frame, with the per-set model (self
        inductances $(L_{d,q} + L_{xy})/2$) unless `motor` is given (see
        `pmsmjax.DualCurrentControl`; `alpha_c` also sets the differential mode's
        bandwidth, several times higher).

        `startup`: an `IfStartup` (e.g. `IfStartup.from_drive(drive)`), or None.

        Saturated machines: the controller model (`motor`, by default the drive's)
        keeps its magnetic model, and with `use_map=True` (the default) the controller
        uses it: current references from the map's torque (and its `MTPATable` for
        "mtpa"/"mtpa_fw"), gains from the incremental inductance, decoupling and field
        weakening from the map's flux (`pmsmjax._control._saturated`). `use_map=False`
        drops it: the controller deploys the constants `L_d`, `L_q`, `psi_f` only, as a
        drive without a map would. Without a magnetic model nothing changes.
        """
        dual_ctrl = None
        if dual is not None:


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
        if not use_map and getattr(motor, "magnetic", None) is not None:
            motor = dataclasses.replace(motor, magnetic=None)
        tau_max = 2.0 * drive.tau_rated if tau_max is None else tau_max
        table = None
        if getattr(motor, "magnetic", None) is not None and strategy in ("mtpa", "mtpa_fw"):
            table = MTPATable.from_model(motor.magnetic, drive.k_tau, drive.i_max)
        return cls(
            current=CurrentController(motor=motor, alpha_c=alpha_c,
                                      u_max=drive.inverter.u_lim),
            speed=SpeedController(J_over_np=drive.mechanics.J / drive.motor.n_p,
                                  alpha_s=alpha_s, tau_max=tau_max),
            refs=CurrentRefs(strategy=strategy, i_d=i_d, i_max=drive.i_max, mtpa=table),
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
            if getattr(m, "magnetic", None) is not None:
                tau_ref = map_torque(m.magnetic, self.k_tau, i_ref[..., 0],
                                     i_ref[..., 1])[0]
            else:
                tau_ref = self.k_tau * (m.extended_flux(i_ref[..., 0]) * i_ref[..., 1])
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
            i_q_if = self.startup.signed_amplitude(su)
            m = self.current.motor
            tau_obs = self.k_tau * m.psi_f * i_q_if * jnp.cos(su.off_obs)
            state = eqx.tree_at(lambda s: s.speed.x_I, state,
                                jnp.where(su.lam > 0, state.speed.x_I,
                                          tau_obs).astype(state.speed.x_I.dtype))
        s_state, i_ref, tau_ref = self._references(state, w_hat, w_ref, T_s,
                                                   i_ref_override, speed_mode)
        if su is not None:
            s = self.startup.weight(su)
            # the open-loop current (i_d, i_q_if) in the controller frame (i_d: the
            # stabiliser's, 0 without it)
            i_d_if = self.startup.damping_current(su)
            c_off, s_off = cos_sin(su.off)
            i_if = jnp.stack([c_off * i_d_if - s_off * i_q_if, s_off * i_d_if + c_off * i_q_if])
            i_ref = (1.0 - s) * i_if + s * i_ref
        c_state, u = self.current.step(state.current, i_ref, i_dq, w_hat, T_s)
        startup = state.startup
        if su is not None:  # the stabiliser's rotor speed from this step's voltage
            startup = eqx.tree_at(lambda t: t.w_r, su, self.startup.rotor_speed(
                su, u[..., 0], i_dq[..., 0], self.current.motor, T_s).astype(su.w_r.dtype))
        return FOCState(current=c_state, speed=s_state, dual=state.dual,
                        startup=startup), \
            FOCOutput(u_dq=u, i_ref=i_ref, tau_ref=tau_ref)
