r"""stumper's inverse parallel-model back-EMF estimator with its output filters.

Reference: J.-F. Stumper, D. Paulus, R. Kennel, "A Nonlinear Estimator for Dynamical and
Robust Sensorless Control of Permanent Magnet Synchronous Machines" (cited as `stumper`).

**Model** (stumper (10), with the conventions of this library: $K$ is the PM flux linkage
$\psi_f$ and the back-EMF is $\omega\psi_f$ with the *electrical* speed $\omega$; the
paper's $K\omega_M$ is $\psi_f\omega$). In polar current coordinates $i_{ab} =
\rho\,[\cos\phi, \sin\phi]$, stumper (5)-(9), and with the voltage projected on the
current direction, $u_P$, and on its normal, $u_O$, stumper (11)-(12):

$$\hat e_P = u_P - \hat R\rho - \hat L\dot\rho = -\psi_f\omega\sin(\theta - \phi),\qquad
\hat e_O = -u_O - \hat L\rho\dot\phi = \psi_f\omega\cos(\theta - \phi)$$

(stumper (13)-(14)): $(\hat e_P, \hat e_O)$ is the back-EMF vector in the frame of the
current. Its angle gives the rotor angle (16)-(17), its length the speed (18)-(19).

**Errata corrected here** (tests in `test_parallel_model.py` fail on the printed forms,
which `_parallel_model_sensitivity` keeps, with the paper's sensitivity analysis (21)-(32)
and the closed-form offsets `parallel_model_offset`):

- stumper (17): the case distinction on the sign of $-\hat L\rho\dot\phi - u_O$ is right
  only for $\omega > 0$: that quantity is $\psi_f\omega\cos(\theta - \phi)$ and changes
  sign with the speed, so at negative speed the printed rule adds $\pi$ where it must not
  (a 180 deg error). The correct rule uses the direction of rotation $s = \mathrm{sign}\,
  \omega$: $\hat\theta = \phi + \mathrm{atan2}(-s\hat e_P, s\hat e_O)$. The rotation
  direction is taken from the tracking filter's speed state $z$ (which follows the
  rotation of the raw estimate whatever its half-turn offset, so a wrong initial sign
  corrects itself). (19)'s sign test divides by $\sin(\theta - \phi)$ with the true
  angle, which an estimator does not have; with the estimated angle it returns $s$ by
  construction, so (18)-(19) are $\hat\omega = s|\hat e|/\hat K$.
- Salient machines: in steady state $u = R i + L_q\,di/dt + e_{ext}$ with the *extended*
  back-EMF $e_{ext} = \omega(\psi_f + (L_d - L_q)i_d)$ along the q axis, for any $i_d$.
  So the single inductance that makes the estimated angle exact in steady state is
  $\hat L = L_q$ (`from_drive`'s default: the model's `L_q`), and the speed (18) divides
  by the extended flux $\hat K = \hat\psi_f + (\hat L_d - \hat L_q)\hat i_d$ with $\hat i_d$
  the current along the estimated d axis. The paper's single $L = 7$ mH is
  `from_drive(drive, L_hat=7e-3)` (an isotropic model).

**Saturated machines** (`with_magnetic`, docs/observers.md): the scheduled model takes
the map's apparent $L_d$, $L_q$, $\psi_f$ at the measured current in the previous
estimate's frame. With the apparent $\hat L = L_q$ ($\psi_q = L_q i_q$ exactly) the
argument above holds for the saturated machine: the steady-state extended back-EMF is
$\omega(\psi_d(i) - L_q i_d)$ along the q axis, and the speed (18) divides by that same
extended flux. The $\hat L\dot\rho$ term uses the apparent, not the incremental,
inductance (right in steady state). The filter gains are kept.

**Near $\rho = 0$** (the transform (5)-(6) is undefined at zero current): below
$\rho_{min}$ = `RHO_MIN` (1e-9 A) the current angle $\phi$ is held at its last value (its
increment is zero) and $\rho = 0$; both are computed with the double-`where` pattern, so
values and gradients stay finite (the gradient of $\rho$ there is the zero subgradient,
that of $\phi$ is zero). The estimator itself does not divide by $\rho$: with no current
$(\hat e_P, \hat e_O)$ is the voltage in the held frame minus the filtered $\hat L\dot\rho$
term, and the angle is still the back-EMF's. The raw angle is undefined only where the
estimated back-EMF vanishes (standstill); there (|e| < `E_MIN`) the tracking filter coasts
(its input error is set to zero).

**Discrete time** (timing of `observers._base`): at $t_k$ the estimator has $i_{k-1}$ (in
its state as $\rho_{k-1}, \phi_{k-1}$), $i_k$ and the voltage $u$ held over
$[t_{k-1}, t_k)$.

- Derivative filters stumper (35)-(36), $s/(T_{LP}s + 1)$: the backward difference
  $\Delta/T_s$ with $\Delta = \rho_k - \rho_{k-1}$ (and $\mathrm{wrap}(\phi_k -
  \phi_{k-1})$), the exact mean slope over the interval, into the forward-Euler low pass
  $y_k = y_{k-1} + (T_s/T_{LP})(\Delta/T_s - y_{k-1})$, i.e. $y_k = a y_{k-1} + (1 - a)
  \Delta/T_s$ with $a = 1 - T_s/T_{LP}$ (stable for $T_s < 2T_{LP}$, checked; 0.875 at the
  paper's 16 kHz and 0.5 ms). For the signals of the steady state ($\rho$ constant,
  $\phi$ a ramp of slope $\omega$) the output is exactly the slope: gain 1, no phase
  error. For a sinusoid of frequency $\Omega$ the response is $\frac{1 - e^{-j\Omega
  T_s}}{T_s}\frac{1 - a}{1 - a e^{-j\Omega T_s}}$: the derivative delayed by about
  $T_{LP} + T_s/2$ at low frequency. (The Euler form keeps the discrete step's Jacobian
  within $O(T_s^2)$ of $I + T_sA$ even at $T_s/T_{LP}$ = 0.2.)
- All quantities of (16)-(19) are taken at the interval's midpoint $t_{k-1/2}$ and with
  the exact chords of the sampled vectors, so that the estimate is exact in steady state
  for a voltage that moves the flux between samples with a trapezoidal resistive drop:
  with $h = \mathrm{wrap}(\phi_k - \phi_{k-1})/2$, $\phi_m = \phi_{k-1} + h$,
  $\rho_m = (\rho_{k-1} + \rho_k)/2$, $u_P$, $u_O$ by (11)-(12) at $\phi_m$, the mean
  current $[\rho_m\cos h, \tfrac12(\rho_k - \rho_{k-1})\sin h]$ in the $\phi_m$ frame for
  the resistive drop, and the current's chord rate $[\dot\rho_f\cos h,
  \rho_m\tfrac{2}{T_s}\sin(\dot\phi_f T_s/2)]$ for the inductive one. The raw estimate
  $\hat\theta_m$ is the angle at $t_{k-1/2}$; the speed (18) inverts the back-EMF's
  chord, $\tfrac{2}{T_s}\arcsin(|\hat e|T_s/(2\hat K))$.
- Tracking filter stumper (37)-(38), $\dot z = v_1\varepsilon$, $\dot{\tilde\theta} = z +
  v_2\varepsilon$, $\varepsilon = \hat\theta - \tilde\theta$: the input error is taken at
  the midpoint against the filter's own prediction, $\varepsilon = \mathrm{wrap}(\hat\theta_m -
  \tilde\theta_{k-1} - z_{k-1}T_s/2)$, then forward Euler over $T_s$. At constant speed
  the equilibrium is $z = \omega$, $\tilde\theta = \theta$ exactly; under a constant
  acceleration $c$ (electrical) it lags by $c/v_1$ (stumper (39) with $c = n_p\dot
  \omega_M$). Poles: $s^2 + v_2 s + v_1$ (the paper's $v_1 = 16000$, $v_2 = 253$ give
  real poles at -125 and -128 1/s, the "8 ms" time constants).
- Speed: (18) at the midpoint, then the forward-Euler first-order low pass with time
  constant $T_\omega$ (stumper: 2 ms).

The estimate returned at $t_k$ is the tracking filter's angle $\tilde\theta_k$ and the
low-passed speed.

**Error dynamics** (for `pmsmjax.analysis`): at an operating point (speed $\omega$,
current $i_0$ held in the estimated frame by an ideal current controller), the current
is $e^{\tilde\theta J}i_0$, so $\rho$ is constant and $\dot\phi = \dot{\tilde\theta}$, and
the voltage contains $L\,di/dt$ with that rate. The rate the current turns at depends on
the estimate, which depends on the voltage: an algebraic loop, solved for
$\dot{\tilde\theta}$ by Newton steps inside `error_rhs`. Its gain is about
$v_2\hat L\rho/(\psi_f\omega)$ (motoring); it reaches 1 at low speed and high current
(for `stumper_mt5` with rated current near 150 rpm), where ideal current control in the
estimated frame is no longer a well-posed model of the loop (a real current controller
with finite bandwidth breaks the loop). The equilibria have a closed form
(`fast_equilibria`, the default route of `analysis.equilibria`, tested against the
generic route).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import back_emf_angle, cos_sin, rotate, wrap_angle
from .._plant._params import Drive, PMSMParams
from .._validate import check_positive, is_concrete
from ._base import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)


#: Below this current magnitude (A) the current angle is held (see the module docstring).
RHO_MIN = 1e-9
#: Below this back-EMF magnitude (V) the raw angle is undefined and the filter coasts.
E_MIN = 1e-9
#: Newton steps for the algebraic loop of the error dynamics.
_N_NEWTON = 4


def polar(i_ab, phi_hold=0.0):
    r"""stumper (5)-(6): current magnitude $\rho$ (A) and angle $\phi$ (rad, in
    (-pi, pi]) of `i_ab` (A, `(2,)`). Below `RHO_MIN` $\rho = 0$ and $\phi$ = `phi_hold`
    (rad), with finite (zero) gradients."""
    i_ab = jnp.asarray(i_ab)
    r2 = i_ab[..., 0] ** 2 + i_ab[..., 1] ** 2
    ok = r2 > RHO_MIN ** 2
    a = jnp.where(ok, i_ab[..., 0], 1.0)
    b = jnp.where(ok, i_ab[..., 1], 0.0)
    rho = jnp.where(ok, jnp.sqrt(a * a + b * b), 0.0)
    phi = jnp.where(ok, jnp.arctan2(b, a), phi_hold)
    return rho, phi


def projections(u_ab, phi):
    """stumper (11)-(12): `(u_P, u_O)` (V) of `u_ab` (V) on the current direction `phi`
    (rad) and (with the paper's sign) on its normal."""
    c, s = cos_sin(phi)
    return u_ab[..., 0] * c + u_ab[..., 1] * s, u_ab[..., 0] * s - u_ab[..., 1] * c


def backemf_polar(u_P, u_O, rho, rho_dot, phi_dot, R_hat, L_hat):
    """stumper (13)-(14) with the model's parameters: the back-EMF along the current,
    `e_P = u_P - R rho - L rho_dot`, and along its normal, `e_O = -u_O - L rho phi_dot`
    (V)."""
    return u_P - R_hat * rho - L_hat * rho_dot, -u_O - L_hat * rho * phi_dot


def parallel_model_angle(e_P, e_O, phi, s):
    r"""stumper (16)-(17), corrected: $\hat\theta = \phi + \mathrm{atan2}(-s e_P, s e_O)$
    (rad, not wrapped) for the rotation direction `s` (+1 or -1): the back-EMF's angle
    (`back_emf_angle`) in the frame of the current, plus that frame's angle `phi`. The
    printed rule is `parallel_model_angle_printed` (`_parallel_model_sensitivity`)."""
    return phi + back_emf_angle(jnp.stack([e_P, e_O], -1), s)


class ParallelModelState(eqx.Module):
    """State of `ParallelModelObserver`.

    - `rho_prev` (A), `phi_prev` (rad): polar coordinates of the previous current sample.
    - `rho_dot` (A/s), `phi_dot` (rad/s): the filtered derivatives stumper (35)-(36).
    - `theta` (rad, wrapped), `z` (rad/s): the tracking filter stumper (37)-(38).
    - `w` (rad/s): the low-passed speed estimate (18)-(19).
    - `started`: False until the first sample has been seen.
    """

    rho_prev: jnp.ndarray
    phi_prev: jnp.ndarray
    rho_dot: jnp.ndarray
    phi_dot: jnp.ndarray
    theta: jnp.ndarray
    z: jnp.ndarray
    w: jnp.ndarray
    started: jnp.ndarray


_COORDS = ErrorCoordinates(
    names=("rho_dot", "phi_dot", "theta", "w", "w_lp"),
    units=("A/s", "rad/s", "rad", "rad/s", "rad/s"), angle=2,
    doc=("current-magnitude rate: true (0 at the operating point) minus filtered, "
         "stumper (35)",
         "current-angle rate: true speed minus filtered, stumper (36)",
         "angle error theta - theta_hat (tracking filter output), stumper (40)",
         "speed error: true speed minus the tracking filter's state z, stumper (37)",
         "speed error: true speed minus the low-passed speed estimate (18)-(19)"))

_DESIGN_UNITS = {
    "v1": "1/s^2, tracking-filter gain stumper (37)",
    "v2": "1/s, tracking-filter gain stumper (38)",
    "T_LP": "s, time constant of the derivative filters stumper (35)-(36)",
    "T_w": "s, time constant of the speed low pass (stumper Sec. IV-D)",
}


class ParallelModelObserver(AbstractObserver):
    r"""Inverse parallel-model estimator of stumper (16)-(19) with its filters
    (35)-(38) and the speed low pass; see the module docstring for the equations, the
    corrections and the discretisation.

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`): $\hat R$ = `R_s` (Ohm), the
      single inductance $\hat L$ = `L_q` (H; exact angle in steady state for a salient
      machine), $\hat K$ = `psi_f` (V s) with `L_d` (H) for the extended flux of (18).
    - `v1`: tracking-filter gain (1/s^2), default 16000 (stumper).
    - `v2`: tracking-filter gain (1/s), default 253 (stumper).
    - `T_LP`: derivative-filter time constant (s), default 0.5 ms (stumper Sec. VI).
    - `T_w`: speed low-pass time constant (s), default 2 ms (stumper Sec. IV-D).
    """

    paper_motor: ClassVar[str | None] = "stumper_mt5"
    paper_T_s: ClassVar[float | None] = 62.5e-6
    tunable_kinds: ClassVar[dict[str, str]] = {"T_LP": "time"}
    #: the tracking filter (37)-(38), s^2 + v2 s + v1: the tuner searches w_tf, zeta_tf
    tuning_coordinates: ClassVar[dict[str, tuple[str, str]]] = {
        "w_tf": ("rad/s", "tracking"), "zeta_tf": ("-", "damping")}
    tuning_replaces: ClassVar[tuple[str, ...]] = ("v1", "v2")
    c_emitter: ClassVar[str | None] = "_stumper:emit"
    motor: PMSMParams
    v1: float
    v2: float
    T_LP: float
    T_w: float

    coordinates: ClassVar[ErrorCoordinates] = _COORDS
    design_units: ClassVar[dict[str, str]] = _DESIGN_UNITS
    extras: ClassVar[dict[str, str]] = {
        "theta_raw_hat": "rad, unfiltered position estimate stumper (16)-(17) (corrected), "
                         "at t_k",
        "w_raw_hat": "rad/s, unfiltered speed estimate stumper (18)-(19), electrical",
        "e_ab_hat": "V, estimated (extended) back-EMF, stationary frame (2,), at "
                    "t_{k-1/2}",
    }
    # T_LP >= 0.5 x 0.5 ms keeps the forward-Euler filters stable down to 4 kHz
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "v1": (0.1, 10.0), "v2": (0.2, 5.0), "T_LP": (0.5, 4.0)}

    def __init__(self, motor: PMSMParams, v1=16000.0, v2=253.0, T_LP=0.5e-3, T_w=2e-3, *,
                 magnetic=None):
        if not isinstance(motor, PMSMParams):
            raise ValueError(f"`ParallelModelObserver(motor=...)` must be a `PMSMParams` "
                             f"(the observer's machine model); got {type(motor).__name__}.")
        self.motor, self.magnetic = motor, magnetic
        self.v1, self.v2, self.T_LP, self.T_w = v1, v2, T_LP, T_w

    def __check_init__(self):
        owner = "ParallelModelObserver"
        check_positive(owner, "v1", self.v1, "1/s^2")
        check_positive(owner, "v2", self.v2, "1/s")
        check_positive(owner, "T_LP", self.T_LP, "s")
        check_positive(owner, "T_w", self.T_w, "s")

    # --- design -----------------------------------------------------------------------
    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   L_hat: float | None = None, **design):
        """stumper's design for `drive`: v1 = 16000 1/s^2, v2 = 253 1/s, T_LP = 0.5 ms,
        T_w = 2 ms, with the drive's machine as the model (the estimator's inductance is
        its `L_q`).

        - `motor`: the observer's machine model (default the drive's).
        - `L_hat`: a single model inductance (H) for both axes, e.g. the paper's 7 mH
          for `stumper_mt5` (replaces the model's `L_d` and `L_q`).
        - `design`: design parameters by name (`design_units`).
        """
        if not isinstance(drive, Drive):
            raise ValueError(f"`ParallelModelObserver.from_drive(drive=...)` must be a "
                             f"`Drive`; got {type(drive).__name__}.")
        motor = drive.three_phase_motor if motor is None else motor
        if L_hat is not None:
            check_positive("ParallelModelObserver.from_drive", "L_hat", L_hat, "H")
            motor = eqx.tree_at(lambda m: (m.L_d, m.L_q), motor, (L_hat, L_hat))
        obs = cls(motor)
        return obs.with_design(**design) if design else obs

    def design_parameters(self) -> dict:
        return {"v1": self.v1, "v2": self.v2, "T_LP": self.T_LP, "T_w": self.T_w}

    @classmethod
    def design_from_tuning(cls, coords: dict, drive=None) -> dict:
        """v1 = w_tf^2, v2 = 2 zeta_tf w_tf from the tracking filter's bandwidth (rad/s)
        and damping (other names pass through)."""
        d = dict(coords)
        if "w_tf" in d:
            w, zeta = d.pop("w_tf"), d.pop("zeta_tf")
            d["v1"], d["v2"] = w ** 2, 2 * zeta * w
        return d

    @classmethod
    def tuning_from_design(cls, design: dict, drive=None) -> dict:
        """w_tf = sqrt(v1), zeta_tf = v2 / (2 sqrt(v1)) (`design_from_tuning` inverted)."""
        d = dict(design)
        if "v1" in d:
            v1, v2 = d.pop("v1"), d.pop("v2")
            d["w_tf"], d["zeta_tf"] = v1 ** 0.5, v2 / (2 * v1 ** 0.5)
        return d

    def with_design(self, **values):
        self._check_design_names(values)
        if not values:
            return self
        new = self._replace(**values)
        new.__check_init__()
        return new

    # --- the estimator ------------------------------------------------------------------
    def _raw(self, u_ab, i_mean, rho_m, phi_m, rho_dot, phi_dot, s, fallback, T_s=None):
        """(16)-(19): raw angle (rad), speed (rad/s), back-EMF (V, stationary frame) and
        whether the angle is defined. `i_mean`: the current in the frame of `phi_m` (A)
        for the resistive drop (`[rho, 0]` in continuous time); `T_s` (s): in discrete
        time the speed inverts the chord of the back-EMF vector (None: continuous)."""
        m = self.motor
        u_P, u_O = projections(u_ab, phi_m)
        e_P, e_O = backemf_polar(u_P, u_O, rho_m, rho_dot, phi_dot, m.R_s, m.L_q)
        # the resistive drop of the mean current (in continuous time [rho, 0])
        e_P = e_P + m.R_s * (rho_m - i_mean[0])
        e_O = e_O - m.R_s * i_mean[1]
        # the back-EMF's angle in the frame of phi_m; undefined (the fallback, with finite
        # gradients) where the back-EMF vanishes
        e2 = e_P * e_P + e_O * e_O
        ok = e2 > E_MIN ** 2
        e_safe = jnp.stack([jnp.where(ok, e_P, 0.0), jnp.where(ok, e_O, 1.0)], -1)
        theta_raw = phi_m + jnp.where(ok, back_emf_angle(e_safe, s), fallback - phi_m)
        e_mag = jnp.where(ok, jnp.sqrt(jnp.where(ok, e2, 1.0)), 0.0)
        K_ext = m.extended_flux(rho_m * jnp.cos(phi_m - theta_raw))
        if T_s is None:
            w_abs = e_mag / K_ext
        else:  # |chord| = 2 K sin(w T_s / 2) / T_s over one interval
            w_abs = (2.0 / T_s) * jnp.arcsin(jnp.clip(0.5 * T_s * e_mag / K_ext, 0.0, 0.99))
        e_ab = rotate(jnp.stack([e_P, e_O]), phi_m)
        return theta_raw, s * w_abs, e_ab, ok

    def init(self, theta0=0.0, w0=0.0) -> ParallelModelState:
        theta0 = jnp.asarray(theta0)
        w0 = jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        zero = jnp.zeros((), dtype)
        w0 = w0.astype(dtype)
        return ParallelModelState(
            rho_prev=zero, phi_prev=zero, rho_dot=zero, phi_dot=w0,
            theta=wrap_angle(theta0.astype(dtype)), z=w0, w=w0,
            started=jnp.asarray(False))

    def check_values(self, T_s) -> None:
        super().check_values(T_s)
        self.check_sampling(T_s)

    def check_sampling(self, T_s) -> None:
        """`ValueError` unless T_s < 2 min(T_LP, T_w) (forward-Euler filters), for
        concrete values."""
        if not is_concrete((T_s, self.T_LP, self.T_w)):
            return
        # plain floats: a JAX comparison of concrete arrays would itself be traced under
        # `jit` (the observer closed over after `pmsmjax.astype`)
        bound = 2.0 * min(float(self.T_LP), float(self.T_w))
        if not float(T_s) < bound:
            raise ValueError(
                f"`ParallelModelObserver.step(T_s=...)` must be below 2 min(T_LP, T_w) = "
                f"{bound!r} s (forward-Euler filters); got {T_s!r}.")

    def step(self, state: ParallelModelState, meas: Measurement, T_s):
        self.check_sampling(T_s)
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        dtype = state.theta.dtype
        i_ab = jnp.asarray(meas.i_ab).astype(dtype)
        u_ab = jnp.asarray(meas.u_ab).astype(dtype)
        rho, phi = polar(i_ab, state.phi_prev)
        d_rho = rho - state.rho_prev
        h = 0.5 * wrap_angle(phi - state.phi_prev)
        # the sampled current in the frame of the midpoint angle phi_m: its chord
        # (i_k - i_{k-1}) = [d_rho cos h, 2 rho_m sin h] and its trapezoidal mean
        # [rho_m cos h, (d_rho / 2) sin h]
        rho_m = 0.5 * (rho + state.rho_prev)
        phi_m = state.phi_prev + h
        c = T_s / self.T_LP
        rho_dot = state.rho_dot + c * (d_rho / T_s - state.rho_dot)
        phi_dot = state.phi_dot + c * (2.0 * h / T_s - state.phi_dot)
        i_mean = jnp.stack([rho_m * jnp.cos(h), 0.5 * d_rho * jnp.sin(h)])
        s = jnp.where(state.z >= 0, 1.0, -1.0).astype(dtype)
        pred = state.theta + 0.5 * T_s * state.z
        # the chord of the current over the interval from the filtered rates, in the
        # midpoint frame: [rho_dot cos h, 2 rho_m sin(phi_dot T_s / 2) / T_s]
        phi_dot_chord = (2.0 / T_s) * jnp.sin(0.5 * T_s * phi_dot)
        theta_raw, w_raw, e_ab, _ = self._raw(u_ab, i_mean, rho_m, phi_m,
                                              rho_dot * jnp.cos(h), phi_dot_chord, s,
                                              pred, T_s)
        eps = wrap_angle(theta_raw - pred)
        z = state.z + T_s * self.v1 * eps
        theta = wrap_angle(state.theta + T_s * (state.z + self.v2 * eps))
        w = state.w + (T_s / self.T_w) * (w_raw - state.w)
        go = state.started

        def pick(new, old):
            return jnp.where(go, new, old).astype(dtype)

        new = ParallelModelState(
            rho_prev=rho.astype(dtype), phi_prev=phi.astype(dtype),
            rho_dot=pick(rho_dot, state.rho_dot), phi_dot=pick(phi_dot, state.phi_dot),
            theta=pick(theta, state.theta), z=pick(z, state.z), w=pick(w, state.w),
            started=jnp.ones_like(state.started))
        extras = {"theta_raw_hat": pick(wrap_angle(theta_raw + 0.5 * T_s * z),
                                        state.theta),
                  "w_raw_hat": pick(w_raw, state.w),
                  "e_ab_hat": jnp.where(go, e_ab, jnp.zeros_like(e_ab)).astype(dtype)}
        return new, Estimate(theta_hat=new.theta, w_hat=new.w, extras=extras)

    # --- analysis ---------------------------------------------------------------------
    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """Continuous error dynamics at `op` (module docstring): the true rotor is put at
        angle 0 (the dynamics do not depend on it), the current is $e^{\\tilde\\theta J}
        i_0$, the voltage the true machine needs for it (with the $L\\,di/dt$ of the
        current turning with the estimated frame), and the algebraic loop solved by
        Newton steps for the frame's rate."""
        x = jnp.asarray(x)
        x_rho, x_phi, x_th, x_w, x_lp = (x[i] for i in range(5))
        w = jnp.asarray(op.w_m, x.dtype)
        i0 = jnp.asarray(op.i_dq, x.dtype)
        th_t = -x_th
        z = w - x_w
        s = jnp.where(z >= 0, 1.0, -1.0).astype(x.dtype)
        i_ab = rotate(i0, th_t)  # = rotor-frame current (rotor at angle 0)
        # the current's angle in the estimated frame, gamma = phi - theta_tilde (held at
        # 0 without current)
        rho, gamma = polar(i0)
        rho_dot_f = -x_rho
        phi_dot_f = w - x_phi
        Ld, Lq = plant.L_d, plant.L_q
        m = self.motor

        # the voltage the true machine needs, affine in the rate p the current turns at
        # (rotor-frame current derivative (p - w) J i; the rotor is at angle 0):
        # u(p) = u0 + p u1, u1 = L J i
        Ji = jnp.stack([-i_ab[1], i_ab[0]])
        LJi = jnp.stack([Ld * Ji[0], Lq * Ji[1]])
        psi = jnp.stack([Ld * i_ab[0] + plant.psi_f, Lq * i_ab[1]])
        u0 = plant.R_s * i_ab - w * LJi + w * jnp.stack([-psi[1], psi[0]])
        phi = th_t + gamma
        P0, O0 = projections(u0, phi)
        P1, O1 = projections(LJi, phi)
        # (13)-(14): e_P = A_P + p B_P, e_O = A_O + p B_O
        A_P, A_O = backemf_polar(P0, O0, rho, rho_dot_f, phi_dot_f, m.R_s, m.L_q)
        B_P, B_O = P1, -O1

        def raw(p):
            """(16)-(17) relative to the filter's angle, eps = theta_raw - theta_tilde
            = gamma + back_emf_angle(e, s), as one angle of the back-EMF e = (e_P, e_O)
            turned by gamma; with |e|^2 and the slope d eps / dp."""
            e_P, e_O = A_P + p * B_P, A_O + p * B_O
            r2 = jnp.maximum(e_P * e_P + e_O * e_O, E_MIN ** 2)
            eps = back_emf_angle(rotate(jnp.stack([e_P, e_O]), gamma), s)
            return eps, r2, (e_P * B_O - e_O * B_P) / r2

        # Newton steps on p - z - v2 eps(p) = 0 (unrolled: the loop is smooth and well
        # conditioned where the error model is well posed, see the module docstring)
        p = phi_dot_f
        for _ in range(_N_NEWTON):
            eps, _, deps = raw(p)
            dg = 1.0 - self.v2 * deps
            dg = jnp.where(jnp.abs(dg) > 1e-6, dg, 1e-6)
            p = p - (p - z - self.v2 * eps) / dg
        eps, r2, _ = raw(p)
        # (18)-(19): |e| over the extended flux, i_d along the raw estimate's d axis
        K_ext = m.extended_flux(rho * jnp.cos(gamma - eps))
        w_raw = s * jnp.sqrt(r2) / K_ext
        dx_th = w - p
        dx_w = -self.v1 * eps
        dx_phi = -(p - phi_dot_f) / self.T_LP
        dx_rho = -x_rho / self.T_LP
        dx_lp = -(w_raw - (w - x_lp)) / self.T_w
        return jnp.stack([dx_rho, dx_phi, dx_th, dx_w, dx_lp])

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        r"""The equilibria in closed form (the route `analysis.equilibria` takes with
        `method="auto"`; `test_parallel_model_sensitivity.py` checks it against the
        generic route). At an equilibrium the filters are at rest ($\dot\rho_f = 0$,
        $\dot\phi_f = z = \omega$) and the raw estimate equals the filter's angle, so the
        estimated back-EMF $\hat e = \omega\psi_{ext}e^{-\Delta\theta J}e_2 - \Delta R\,i_0
        - \Delta L\,\omega J i_0$ (estimated frame, $\Delta\theta = \hat\theta - \theta$)
        lies on the estimated q axis with the sign of the speed:
        $\omega\psi_{ext}\sin\Delta\theta = \Delta R\,i_{0d} - \Delta L\,\omega i_{0q}$ and
        $s\,\hat e_q > 0$ (`parallel_model_offset(frame="estimated")`). Both branches of the
        sine are tried (Newton steps for the salient machine's $\psi_{ext}$); the speed
        low pass settles at the speed estimate's bias. Stability from the Jacobian of
        `error_rhs` (Routh-Hurwitz). `n_grid` is not used."""
        del n_grid
        from ..analysis._equilibria import Equilibria
        from ..analysis._linearize import charpoly, routh_hurwitz

        dtype = jnp.result_type(op.w_m, float)
        w = jnp.asarray(op.w_m, dtype)
        i0 = jnp.asarray(op.i_dq, dtype)
        m = self.motor
        dR, dL = m.R_s - plant.R_s, m.L_q - plant.L_q
        num = dR * i0[0] - dL * w * i0[1]
        w_s = jnp.where(w != 0, w, 1.0)
        s = jnp.where(w >= 0, 1.0, -1.0)

        def psi_ext(x):
            return plant.extended_flux(i0[0] * jnp.cos(x) - i0[1] * jnp.sin(x))

        def branch(k):
            sn = jnp.clip(num / (w_s * plant.psi_f), -1.0, 1.0)
            x = jnp.arcsin(sn) if k == 0 else jnp.pi - jnp.arcsin(sn)
            for _ in range(8):  # Newton on w psi_ext(x) sin x - num (exact if isotropic)
                h = w_s * psi_ext(x) * jnp.sin(x) - num
                dpsi = (plant.L_d - plant.L_q) * (-i0[0] * jnp.sin(x) - i0[1] * jnp.cos(x))
                dh = w_s * (dpsi * jnp.sin(x) + psi_ext(x) * jnp.cos(x))
                x = x - h / jnp.where(jnp.abs(dh) > 1e-12, dh, 1e-12)
            e_q = w * psi_ext(x) * jnp.cos(x) - dR * i0[1] - dL * w * i0[0]
            ok = (s * e_q > 0) & (jnp.abs(w_s * psi_ext(x) * jnp.sin(x) - num)
                                  <= 1e-9 * (jnp.abs(w_s) * plant.psi_f + jnp.abs(num)))
            return wrap_angle(-x), ok

        th = []
        oks = []
        for k in (0, 1):
            t, ok = branch(k)
            th.append(t)
            oks.append(ok)
        th = jnp.stack(th)
        ok = jnp.stack(oks) & (w != 0)
        ok = ok.at[1].set(ok[1] & (jnp.abs(wrap_angle(th[1] - th[0])) > 1e-9))

        def full(t):
            x = jnp.stack([jnp.zeros_like(t), jnp.zeros_like(t), t, jnp.zeros_like(t),
                           jnp.zeros_like(t)])
            return x.at[4].set(self.T_w * self.error_rhs(x, op, plant)[4])

        xs = jnp.stack([full(t) for t in th])
        scale = self.error_scale(op, plant)
        rate = jnp.where(jnp.abs(w) > 0, jnp.abs(w), 1.0)
        res = jnp.stack([jnp.max(jnp.abs(self.error_rhs(x, op, plant) / (scale * rate)))
                         for x in xs])
        A = jnp.stack([jax.jacfwd(lambda v: self.error_rhs(v, op, plant))(x) for x in xs])
        c = charpoly(A * rate ** -1)
        tol = float(jnp.finfo(dtype).eps) ** 0.6
        ok = ok & (res < 1e3 * tol)
        tangent = jnp.zeros_like(ok)  # the equilibria are simple roots of the sine
        stable = ok & routh_hurwitz(c)
        R = 6
        pad = lambda a, v: jnp.concatenate(  # noqa: E731
            [a, jnp.full((R - 2,) + a.shape[1:], v, a.dtype)])
        order = jnp.argsort(jnp.where(ok, th, jnp.inf))
        th, xs, ok, stable, res, A = (a[order] for a in (th, xs, ok, stable, res, A))
        tangent = tangent[order]
        nan = jnp.nan
        n = jnp.sum(ok)
        return Equilibria(
            theta=pad(jnp.where(ok, th, nan), nan),
            x=pad(jnp.where(ok[:, None], xs, nan), nan),
            valid=pad(ok, False), stable=pad(stable, False), tangent=pad(tangent, False),
            residual=pad(jnp.where(ok, res, nan), nan),
            principal=jnp.argmin(jnp.where(ok, jnp.abs(th), jnp.inf)).astype(jnp.int32),
            n=n.astype(jnp.int32),
            status=jnp.where(w == 0, -1, jnp.where(n == 0, 2, 0)).astype(jnp.int32),
            jacobian=pad(jnp.where(ok[:, None, None], A, nan), nan))

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        del plant
        aw = jnp.abs(op.w_m)
        aw = jnp.where(aw > 0, aw, 1.0)
        rho = jnp.sqrt(jnp.sum(jnp.asarray(op.i_dq) ** 2))
        rho = jnp.where(rho > 0, rho, 1.0)
        return jnp.stack([rho * aw, aw, jnp.ones_like(aw), aw, aw])

    def error_state(self, state: ParallelModelState, truth: PlantPoint, plant: PMSMParams):
        del plant
        w = truth.w_m
        return jnp.stack([-state.rho_dot, w - state.phi_dot,
                          wrap_angle(truth.theta - state.theta), w - state.z, w - state.w])

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> ParallelModelState:
        del plant
        x = jnp.asarray(x)
        w = jnp.asarray(truth.w_m, x.dtype)
        rho, phi = polar(jnp.asarray(truth.i_ab, x.dtype))
        return ParallelModelState(
            rho_prev=rho, phi_prev=phi, rho_dot=-x[0], phi_dot=w - x[1],
            theta=wrap_angle(truth.theta - x[2]), z=w - x[3], w=w - x[4],
            started=jnp.asarray(True))
