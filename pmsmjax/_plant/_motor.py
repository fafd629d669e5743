r"""Continuous-time PMSM plant (electrical + mechanical), in a form diffrax integrates.

Quantities in rotor coordinates carry `_dq`, stationary ones `_ab`. The state is
`PlantState(i_dq, theta, w_m, i_xy)`: stator current in rotor coordinates (A), electrical
rotor angle (rad, unwrapped), electrical speed (rad/s) and, for a dual three-phase
machine only, the x-y subspace current (A, stationary x-y frame).

Three-phase machine, with $\psi_{dq} = L i_{dq} + \psi_{pm}(\theta)$,
$L = \mathrm{diag}(L_d, L_q)$:

$$L \frac{d i_{dq}}{dt} = u_{dq} - R_s i_{dq} - \omega_m J \psi_{dq}
  - \omega_m \frac{\partial \psi_{pm}}{\partial \theta}, \qquad
  u_{dq} = e^{-\theta J} u_{ab},$$

$$\tau_M = \tfrac32 n_p \left[\psi_{dq} \times i_{dq}
  + i_{dq}\cdot\frac{\partial \psi_{pm}}{\partial\theta}\right], \qquad
  \frac{J_M}{n_p}\frac{d\omega_m}{dt} = \tau_M - \frac{B}{n_p}\omega_m - \tau_L, \qquad
  \frac{d\theta}{dt} = \omega_m.$$

This torque is the one the power balance requires:
$\tfrac32 u\cdot i = \tfrac32 R_s |i|^2 + \frac{d}{dt}\left(\tfrac34 i^T L i\right)
+ \tau_M \omega_m / n_p$ (`power_balance` returns the terms).

Dual three-phase (VSD, amplitude-invariant): the alpha-beta subspace follows the
equations above with $\tfrac32$ replaced by 3; PM-flux harmonics of order $6k\pm1$ with
$k$ odd (5, 7, 17, 19, ...) leave alpha-beta and excite the x-y subspace,
$L_{xy}\, d i_{xy}/dt = u_{xy} - R_s i_{xy} - \omega_m \partial\psi_{pm,xy}/\partial\theta$,
where $\psi_{pm,xy}$ is the complex conjugate of the alpha-beta vector the same harmonic
would have in a three-phase machine (derived from `vsd_matrix`, tested).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import cos_sin, park
from ._inverter import dead_time_error_ab, dead_time_error_vsd
from ._magnetic import solve2
from ._params import (
    DualThreePhaseParams,
    EMFHarmonics,
    Inverter,
    Mechanics,
    PMSMParams,
    _is_dual,
    _three_phase,
    _torque_factor,
)


class PlantState(eqx.Module):
    """State of the plant (see the module docstring)."""

    i_dq: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray
    i_xy: jnp.ndarray | None = None


class PlantInput(eqx.Module):
    """Inputs held constant over one integration interval.

    - `u_ab`: stator voltage, stationary frame (V, (2,)).
    - `tau_L`: load torque (N m).
    - `u_xy`: x-y subspace voltage of a dual three-phase machine (V, (2,)); ignored for a
      three-phase machine.
    - `free`: 1 for a free rotor; 0 when a load machine holds the speed constant (the
      mechanical equation is switched off and `w_m` stays at its initial value).
    """

    u_ab: jnp.ndarray
    tau_L: jnp.ndarray
    u_xy: jnp.ndarray | None = None
    free: float = 1.0


# Component form: the same Modules with every 2-vector held as a tuple `(x, y)` of its
# components. `simulate` carries the plant in this form, so that its step is element-wise
# arithmetic without stacking and slicing, which XLA compiles to fewer and faster loops,
# forward and reverse (measured when it was chosen: `git log -p BENCHMARKS.md`).

def _pair(v):
    return None if v is None else (v[..., 0], v[..., 1])


def _stack(v):
    return None if v is None else jnp.stack(v, -1)


def split_state(y: PlantState) -> PlantState:
    """`y` in component form (2-vectors as `(x, y)` tuples)."""
    return PlantState(i_dq=_pair(y.i_dq), theta=y.theta, w_m=y.w_m, i_xy=_pair(y.i_xy))


def join_state(y: PlantState) -> PlantState:
    """Inverse of `split_state`."""
    return PlantState(i_dq=_stack(y.i_dq), theta=y.theta, w_m=y.w_m, i_xy=_stack(y.i_xy))


def split_input(u: PlantInput) -> PlantInput:
    """`u` in component form (2-vectors as `(x, y)` tuples)."""
    return PlantInput(u_ab=_pair(u.u_ab), tau_L=u.tau_L, u_xy=_pair(u.u_xy), free=u.free)


def _is_zero(u_dt) -> bool:
    """`u_dt` is `None` or a Python zero: no inverter error (a static decision)."""
    return u_dt is None or (isinstance(u_dt, (int, float)) and u_dt == 0)


def _xy_order(h: int) -> bool:
    """True if a PM harmonic of signed order h maps to the x-y subspace of a DTP machine."""
    return abs(h) % 12 in (5, 7)


class PMSM(eqx.Module):
    """PMSM plant: `vector_field(t, y, args)` with the signature of `diffrax.ODETerm`.

    **Arguments:**

    - `motor`: `PMSMParams` or `DualThreePhaseParams`.
    - `mechanics`: `Mechanics`.
    - `inverter`: optional `Inverter` whose dead-time error (`u_dt`, `i_dt`) the windings
      see: the input voltage is then the *commanded* one, and the machine receives it
      less the error at its present phase currents (`pmsmjax._plant._inverter`), evaluated
      continuously inside each integration step. `None` or `u_dt = 0`: ideal.
    """

    motor: PMSMParams | DualThreePhaseParams
    mechanics: Mechanics
    inverter: Inverter | None = None

    @property
    def _dead_time(self) -> bool:
        """Whether the inverter's voltage error is modelled (skipped when `u_dt` is a
        Python zero or `None`, so an ideal inverter costs nothing)."""
        return self.inverter is not None and not _is_zero(self.inverter.u_dt)

    @property
    def dual(self) -> bool:
        return _is_dual(self.motor)

    @property
    def _ab(self) -> PMSMParams:
        return _three_phase(self.motor)

    @property
    def k_tau(self):
        """Torque factor: 1.5 n_p (three-phase) or 3 n_p (dual three-phase)."""
        return _torque_factor(self.motor)

    # -- PM flux, split by subspace -----------------------------------------------------
    def _harmonics(self, xy: bool):
        harm = self._ab.harmonics
        if harm is None:
            return ()
        keep = [(h, a, ph) for h, a, ph in zip(harm.order, harm.amplitude, harm.phase)
                if (self.dual and _xy_order(h)) == xy]
        return tuple(keep)

    def _ab_params(self) -> PMSMParams:
        """Alpha-beta parameters with only the harmonics that live in alpha-beta."""
        p = self._ab
        if not self.dual or p.harmonics is None:
            return p
        keep = self._harmonics(xy=False)
        harm = None if not keep else EMFHarmonics(
            order=[h for h, _, _ in keep],
            amplitude=jnp.stack([a for _, a, _ in keep]),
            phase=jnp.stack([ph for _, _, ph in keep]),
        )
        return eqx.tree_at(lambda q: q.harmonics, p, harm, is_leaf=lambda x: x is None)

    def psi_pm_dq(self, theta):
        """PM flux linkage of the alpha-beta subspace in rotor coordinates (V s)."""
        return self._ab_params().psi_pm_dq(theta)

    def dpsi_pm_xy_dtheta(self, theta):
        """d psi_pm,xy / d theta of a dual three-phase machine (V s/rad, stationary x-y)."""
        p = self._ab
        d = jnp.zeros(jnp.shape(theta) + (2,), dtype=jnp.result_type(theta, float))
        for h, a, ph in self._harmonics(xy=True):
            ang = h * theta + ph
            amp = p.psi_f * a / abs(h) * h
            # psi_xy = amp/h * (cos(ang), -sin(ang)) -> derivative w.r.t. theta
            d = d + amp * jnp.stack([-jnp.sin(ang), -jnp.cos(ang)], axis=-1)
        return d

    # -- algebraic outputs ---------------------------------------------------------------
    def _flux(self, y: PlantState, p: PMSMParams):
        """`(psi_d, psi_q, L_inc)` of `y` in component form: the flux linkage (V s) with its
        PM harmonics, and the incremental inductances `(L_dd, L_dq, L_qd, L_qq)` (H) of a
        saturated machine (`None` for constant inductances: diag(L_d, L_q))."""
        i_d, i_q = y.i_dq
        psi_pm = p.psi_pm_dq(y.theta)
        if p.magnetic is None:
            return p.L_d * i_d + psi_pm[..., 0], p.L_q * i_q + psi_pm[..., 1], None
        psi_d, psi_q, *l_inc = p.magnetic.flux_and_inductance(i_d, i_q)
        if p.harmonics is not None:  # the harmonics ride on the map's fundamental
            psi_d, psi_q = psi_d + psi_pm[..., 0] - p.psi_f, psi_q + psi_pm[..., 1]
        return psi_d, psi_q, tuple(l_inc)

    def flux_dq(self, y: PlantState):
        """Stator flux linkage in rotor coordinates (V s, (..., 2))."""
        psi_d, psi_q, _ = self._flux(split_state(y), self._ab_params())
        return jnp.stack([psi_d, psi_q], -1)

    def torque(self, y: PlantState):
        """Electromagnetic torque tau_M (N m)."""
        psi = self.flux_dq(y)
        return self._torque(split_state(y), psi[..., 0], psi[..., 1], self._ab_params())

    def _torque(self, y: PlantState, psi_d, psi_q, ab: PMSMParams):
        """`torque` of `y` in component form, from its flux components (V s)."""
        i_d, i_q = y.i_dq
        tau = psi_d * i_q - psi_q * i_d
        if ab.harmonics is not None:
            dpsi = ab.dpsi_pm_dq_dtheta(y.theta)
            tau = tau + (i_d * dpsi[..., 0] + i_q * dpsi[..., 1])
        if self.dual and self._harmonics(xy=True):
            dpsi = self.dpsi_pm_xy_dtheta(y.theta)
            tau = tau + (y.i_xy[0] * dpsi[..., 0] + y.i_xy[1] * dpsi[..., 1])
        return self.k_tau * tau

    # -- dynamics ------------------------------------------------------------------------
    def vector_field(self, t, y: PlantState, args: PlantInput) -> PlantState:
        """Time derivative of the state (`diffrax.ODETerm` signature)."""
        return join_state(self._rates(t, split_state(y), split_input(args)))

    def _rates(self, t, y: PlantState, args: PlantInput) -> PlantState:
        """`vector_field` for state and input in component form (see `split_state`).

        Written per component (d, q), so that the closed loop runs on element-wise
        arithmetic without stacking and slicing 2-vectors.
        """
        del t
        p = self._ab_params()
        m = self.mechanics
        w = y.w_m
        i_d, i_q = y.i_dq
        c, s = cos_sin(y.theta)
        u_a, u_b = args.u_ab
        u_xy = None
        if self.dual:
            u_xy = args.u_xy if args.u_xy is not None else (jnp.zeros_like(u_a),) * 2
        if self._dead_time:  # the windings receive the commanded voltage less the error
            inv = self.inverter
            i_a, i_b = c * i_d - s * i_q, s * i_d + c * i_q  # inv_park(i_dq, theta)
            if self.dual:
                du_ab, du_xy = dead_time_error_vsd(inv.u_dt, inv.i_dt, jnp.stack([i_a, i_b], -1),
                                                   jnp.stack(y.i_xy, -1))
                u_a, u_b = u_a - du_ab[..., 0], u_b - du_ab[..., 1]
                u_xy = (u_xy[0] - du_xy[..., 0], u_xy[1] - du_xy[..., 1])
            else:
                du_a, du_b = dead_time_error_ab(inv.u_dt, inv.i_dt, i_a, i_b)
                u_a, u_b = u_a - du_a, u_b - du_b
        u_d, u_q = c * u_a + s * u_b, c * u_b - s * u_a  # park(u_ab, theta)
        psi_d, psi_q, l_inc = self._flux(y, p)
        emf_d, emf_q = w * -psi_q, w * psi_d  # w J psi
        if p.harmonics is not None:
            dpsi = p.dpsi_pm_dq_dtheta(y.theta)
            emf_d, emf_q = emf_d + w * dpsi[..., 0], emf_q + w * dpsi[..., 1]
        v_d, v_q = u_d - p.R_s * i_d - emf_d, u_q - p.R_s * i_q - emf_q
        if l_inc is None:
            di_dq = (v_d / p.L_d, v_q / p.L_q)
        else:  # L_inc di/dt = v: the flux-linkage equation by the chain rule
            di_dq = solve2(*l_inc, v_d, v_q)
        tau_M = self._torque(y, psi_d, psi_q, p)
        dw = args.free * p.n_p * (tau_M - m.B * w / p.n_p - args.tau_L) / m.J
        if self.dual:
            dpsi = self.dpsi_pm_xy_dtheta(y.theta)
            di_xy = tuple((u - p.R_s * i - w * dpsi[..., j]) / self.motor.L_xy
                          for j, (u, i) in enumerate(zip(u_xy, y.i_xy)))
        else:
            di_xy = None
        return PlantState(i_dq=di_dq, theta=w, w_m=dw, i_xy=di_xy)

    def init(self, theta0=0.0, w_m0=0.0, i_dq0=(0.0, 0.0)) -> PlantState:
        """Initial state: current `i_dq0` (A), angle `theta0` (rad), speed `w_m0` (rad/s)."""
        i_dq = jnp.asarray(i_dq0, dtype=float)
        return PlantState(
            i_dq=i_dq,
            theta=jnp.asarray(theta0, dtype=float),
            w_m=jnp.asarray(w_m0, dtype=float),
            i_xy=jnp.zeros(2) if self.dual else None,
        )

    def power_balance(self, y: PlantState, args: PlantInput):
        """Instantaneous power terms (W): `(p_in, p_cu, dW_mag/dt, p_mech)`.

        `p_in = p_cu + dW_mag/dt + p_mech` holds exactly for the model above.
        """
        p = self._ab_params()
        k = self.k_tau / p.n_p  # 1.5 or 3: power scaling of amplitude-invariant vectors
        dy = self.vector_field(0.0, y, args)
        u_ab, u_xy = jnp.asarray(args.u_ab), args.u_xy
        if self.dual and u_xy is None:
            u_xy = jnp.zeros_like(u_ab)
        if self._dead_time:  # p_in is the power the windings receive
            inv, i_ab = self.inverter, self.i_ab(y)
            if self.dual:
                du_ab, du_xy = dead_time_error_vsd(inv.u_dt, inv.i_dt, i_ab, y.i_xy)
                u_ab, u_xy = u_ab - du_ab, u_xy - du_xy
            else:
                du = dead_time_error_ab(inv.u_dt, inv.i_dt, i_ab[..., 0], i_ab[..., 1])
                u_ab = u_ab - jnp.stack(du, -1)
        u_dq = park(u_ab, y.theta)
        p_in = k * jnp.sum(u_dq * y.i_dq, -1)
        p_cu = k * p.R_s * jnp.sum(y.i_dq ** 2, -1)
        _, _, l_inc = self._flux(split_state(y), p)
        i_d, i_q, di_d, di_q = y.i_dq[..., 0], y.i_dq[..., 1], dy.i_dq[..., 0], dy.i_dq[..., 1]
        if l_inc is None:
            dW = k * (p.L_d * i_d * di_d + p.L_q * i_q * di_q)
        else:  # i . dpsi/dt = i . L_inc di/dt: the rate of the field energy (reciprocal map)
            l_dd, l_dq, l_qd, l_qq = l_inc
            dW = k * (i_d * (l_dd * di_d + l_dq * di_q) + i_q * (l_qd * di_d + l_qq * di_q))
        if self.dual:
            p_in = p_in + k * jnp.sum(u_xy * y.i_xy, -1)
            p_cu = p_cu + k * p.R_s * jnp.sum(y.i_xy ** 2, -1)
            dW = dW + k * self.motor.L_xy * jnp.sum(y.i_xy * dy.i_xy, -1)
        p_mech = self.torque(y) * y.w_m / p.n_p
        return p_in, p_cu, dW, p_mech

    def i_ab(self, y: PlantState):
        """Stator current in the stationary frame (A)."""
        c, s = cos_sin(y.theta)
        i_d, i_q = y.i_dq[..., 0], y.i_dq[..., 1]
        return jnp.stack([c * i_d - s * i_q, s * i_d + c * i_q], -1)  # inv_park
