r"""Extended-state flux observers of zhang2022 and the adaptive full-order baseline.

Reference: M. Zhang, B. Xia, J. Zhang, "Parameter Design and Convergence Analysis of Flux
Observer for Sensorless PMSM Drives", IEEE Trans. Energy Convers., 37(4), 2022,
doi:10.1109/TEC.2022.3177707. The
baseline is the adaptive full-order observer of its reference [21] (M. Hinkkanen et al.,
"Observers for sensorless synchronous motor drives: framework for design and analysis",
IEEE Trans. Ind. Appl., 54(6), 2018, doi:10.1109/TIA.2018.2858753) with the speed law
(53) of zhang2022.

All three observers share one flux model, (10a), (10d), (10e), in the estimator frame
(angle $\hat\theta$, no suffix):

$$\frac{d\hat\psi}{dt} = u - \hat R_s i - \omega_f J \hat\psi + G_1 f(e),\qquad
e = \hat L i - \hat\psi + \hat\psi_f \quad(= \hat L(i - \hat i)),$$

where $\omega_f = \dot{\hat\theta}$ is the speed of the estimator frame and $f$ the
feedback nonlinearity. (10a) prints $\hat\omega$ in place of $\omega_f$; the rotation
term of (4) comes from the frame change, so it is the frame speed, which (10b) makes
$\hat\omega + g_2 f(e)$ (see `_eso_design`'s docstring: same linearisation (15), same
equilibria with the minimum-norm gains).

**Discretisation.** With $\hat\psi_{ab} = e^{\hat\theta J}\hat\psi$ the rotation terms
cancel exactly and the flux equation in stationary coordinates is
$d\hat\psi_{ab}/dt = u_{ab} - \hat R_s i_{ab} + e^{\hat\theta J} G_1 f(e)$. At $t_k$ the
observer receives $i_{ab,k}$ and the voltage $u_{ab}$ held over $[t_{k-1}, t_k)$ and
integrates over that interval:

- voltage: exact for the zero-order hold, $T_s u_{ab}$;
- resistive drop: trapezoid, $\tfrac12 T_s \hat R_s (i_{ab,k-1} + i_{ab,k})$ ($i_{ab,k-1}$
  is kept in the state);
- feedback, frame speed and the extended state: explicit, with the error $e_{k-1}$ at
  $t_{k-1}$ and the gains scheduled at $t_{k-1}$, held constant over the interval. The
  angle advances by $T_s\omega_f$ and the speed state by $T_s g_3 f(e_{k-1})$ (forward
  Euler). The flux correction $G_1 f(e_{k-1})$ is held constant *in the estimator
  frame*, which turns at $\omega_f$ during the interval, so its exact integral is
  $T_s\,\mathrm{sinc}(\omega_f T_s/2)\,e^{(\hat\theta_{k-1} + \omega_f T_s/2)J}
  G_1 f(e_{k-1})$. Rotating it with $\hat\theta_{k-1}$ instead (plain forward Euler)
  lags by $\omega_f T_s/2$ (4.5 deg at rated speed and 8 kHz for `zhang750`) and creates
  a spurious stable equilibrium near 9.5 deg there (`test_eso.py`); with the rule above
  the 8 kHz observer converges, or loses lock, from large initial errors as the
  continuous error dynamics (11) do in the cases tested.

The estimate returned at $t_k$ is the state after this update. At the first sample
($k = 0$) nothing is integrated: the flux is initialised from the observer's model at the
initial angle and the measured current, $\hat\psi_{ab} = e^{\hat\theta_0 J}
(\hat L\, i_0 + \hat\psi_f)$, so that $e_0 = 0$ (the observer trusts its initial angle).

**Saturated machines** (`with_magnetic`, docs/observers.md). The model enters only as
the flux $\hat L i + \hat\psi_f$ of the error signal (10d) and in the gains, which (38),
(17) and (25) compute at every step from the model at the measured current. The
scheduled model evaluates the map's apparent $L_d$, $L_q$, $\psi_f$ at $i_{k-1}$ in the
estimator frame, the current at which (10d) is formed, so that its model flux *is* the
map's $\psi_{dq}(i_{k-1})$: the three observers become flux-map observers (exact in
steady state), and their gains follow the scheduled model (its active flux
$\psi_f + (L_d - L_q) i_d$ from the apparent values).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._frames import park, rotate, wrap_angle
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
from ._eso_design import (
    ESOGains,
    check_design,
    error_dynamics,
    fal,
    psi_a,
)
from ._eso_schedules import (
    FIXED_RATIO_BOUNDS,
    SCALED_38_BOUNDS,
    SCHEDULE_PARAMS,
    ZHANG38_SCALES,
    AbstractGainSchedule,
    ESODesign,
    FixedGains,
    schedule_for,
)
from ._flux_coordinates import (
    flux_error_scale,
    flux_errors,
    flux_estimates,
    model_flux_dq,
    previous_current_dq,
)


# ---------------------------------------------------------------------------------------
# Observers
# ---------------------------------------------------------------------------------------

class FluxObserverState(eqx.Module):
    """State of the flux observers.

    - `psi_ab`: estimated stator flux, stationary frame (V s, (2,)).
    - `theta`: estimated electrical angle, wrapped to (-pi, pi] (rad).
    - `w`: ESO/LESO: the extended state $\\hat\\omega$; AFO: the integral part of the PI
      speed law (53) (rad/s).
    - `i_prev`: current sampled at the previous instant (A, stationary frame).
    - `started`: False until the first sample has been seen.
    """

    psi_ab: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


def _error(motor: PMSMParams, psi_ab, theta, i_ab):
    """Error signal (10d) $e = \\hat L i - \\hat\\psi + \\hat\\psi_f$ in the estimator frame
    at angle `theta`, and the current in that frame."""
    i_dq = park(i_ab, theta)
    return model_flux_dq(motor, i_dq) - park(psi_ab, theta), i_dq


def _flux_init(motor, theta, i_ab):
    return rotate(model_flux_dq(motor, park(i_ab, theta)), theta)


_COORDS = ErrorCoordinates(
    names=("psi_d", "psi_q", "theta", "w"), units=("V s", "V s", "rad", "rad/s"), angle=2,
    doc=("stator-flux error, estimator frame d axis (true minus estimate)",
         "stator-flux error, estimator frame q axis",
         "angle error theta - theta_hat",
         "speed error: true speed minus the speed state (ESO/LESO: the extended state "
         "w_hat; AFO: the integral part of the PI law zhang2022 (53))"))

#: Design parameters of the zhang2022 observers (`ESODesign` fields, fal's `a`, `eta`).
_DESIGN_UNITS = {
    "w2": "rad/s, speed/angle natural frequency zhang2022 (25)",
    "zeta2": "-, speed/angle damping zhang2022 (25)",
    "w_rated": "rad/s, rated electrical speed of the schedule zhang2022 (38)",
    "zeta1_scale": "-, factor on the flux damping of zhang2022 (38), its shape over speed "
                   "kept (zhang38 schedule)",
    "decay_scale": "-, factor on the flux decay rate zeta1 w1 = 1.5 |w0| of zhang2022 (38) "
                   "(zhang38 schedule)",
    "zeta1": "-, flux damping zhang2022 (17) (fixed_ratio / fixed_w1 schedules)",
    "ratio": "-, w1/|w0| (fixed_ratio schedule, the axes of zhang2022 Fig. 1)",
    "w1": "rad/s, flux natural frequency (fixed_w1 schedule)",
    "w_min": "rad/s, speed clamp of w1^2/w0 in zhang2022 (17) (fixed_w1 schedule)",
    "n2": "rad/s per V s, null-space component of g2 beyond zhang2022 (25)",
    "n3": "rad/s^2 per V s, null-space component of g3 beyond zhang2022 (25)",
}
_FAL_UNITS = {"a": "-, fal exponent in (0, 1], zhang2022 (9)",
              "eta": "V s, half-width of fal's linear zone, zhang2022 (9)"}
class AbstractFluxObserver(AbstractObserver):
    """The common base of zhang2022's stator-flux observers (`ESOObserver`,
    `LESOObserver`, `AFOObserver`): the flux estimate, the angle and speed loop (25) and a
    gain schedule `design` over the speed estimate. The analysis's slowly-varying
    certificates and fast-ramp bound (`analysis.lyapunov`, `analysis.fast_ramp`) are
    written for this family and accept any of its members."""

    paper_motor: ClassVar[str | None] = "zhang750"
    paper_T_s: ClassVar[float | None] = 125e-6
    tunable_kinds: ClassVar[dict[str, str]] = {"w2": "tracking", "zeta2": "damping"}
    #: the flux loop as zhang2022 (38)'s schedule with its damping and its decay rate
    #: zeta1 w1 = 1.5 |w0| scaled (`ESODesign`, `zeta1_scale`, `decay_scale`): the paper's
    #: design is the point (1, 1), and the tuned flux gains keep (38)'s shape over speed
    #: (zeta1 rising, w1/|w0| falling with speed), which a fixed ratio cannot (measured in
    #: docs/tuning.md, "Inductance mismatch up to +-50 %"); the AFO keeps
    #: `FIXED_RATIO_BOUNDS`
    tunable_bounds: ClassVar[dict[str, tuple[float, float, float, str]]] = SCALED_38_BOUNDS
    motor: eqx.AbstractVar[PMSMParams]
    design: eqx.AbstractVar[AbstractGainSchedule]

    coordinates: ClassVar[ErrorCoordinates] = _COORDS
    design_units: ClassVar[dict[str, str]] = _DESIGN_UNITS
    extras: ClassVar[dict[str, str]] = {
        "psi_ab_hat": "V s, estimated stator flux, stationary frame (2,)"}
    # tunable design: factors 1/5..5 keep w2 T_s <= 0.2 at 8 kHz (zhang750)
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "w2": (0.2, 5.0), "zeta2": (0.2, 5.0)}

    # --- design -----------------------------------------------------------------------
    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   fixed_at: float | None = None, **design):
        """zhang2022's design for `drive`: flux gains (38)/(17), speed/angle gains (25)
        with `w2` = 2 pi 50 rad/s and `zeta2` = 1 (for the AFO: G1 from (38), speed law
        (53)); ESO: fal `a` = 0.5, `eta` = 0.05 psi_f.

        - `motor`: the observer's machine model (default the drive's).
        - `design`: design parameters by name (`design_units`); `zeta1` with `ratio`
          selects the fixed-ratio schedule, `zeta1`, `w1`, `w_min` the fixed-w1 one.
        - `fixed_at`: freeze every gain at this speed (p.u. of `drive.w_rated`) and zero
          current (`FixedGains`, zhang2022 Fig. 11).
        """
        motor = drive.three_phase_motor if motor is None else motor
        obs = cls(motor, ESODesign.zhang38(drive.w_rated))
        obs = obs.with_design(**design) if design else obs
        if fixed_at is not None:
            check_positive(cls.__name__ + ".from_drive", "fixed_at", fixed_at, "p.u.")
            fixed = FixedGains.at(obs.design, motor, float(fixed_at) * float(drive.w_rated))
            obs = eqx.tree_at(lambda o: o.design, obs, fixed)
        return obs

    def design_parameters(self) -> dict:
        out = {}
        d = self.design
        if isinstance(d, ESODesign):
            out = {"w2": d.w2, "zeta2": d.zeta2, "n2": d.n2, "n3": d.n3}
            out.update({k: getattr(d, k) for k in SCHEDULE_PARAMS[d.schedule]})
            if d.schedule == "zhang38":
                out.update({k: getattr(d, k) for k in ZHANG38_SCALES})
        out = {k: v for k, v in out.items() if k in self.design_units}
        return {**out, **self._fal_parameters()}

    def _fal_parameters(self) -> dict:
        return {}

    def with_design(self, **values):
        owner = f"{type(self).__name__}.with_design"
        self._check_design_names(values, owner)
        fal_values = {k: values.pop(k) for k in list(values) if k in _FAL_UNITS}
        obs = self
        if values:
            d = self.design
            if not isinstance(d, ESODesign):
                raise ValueError(f"`{owner}`: the gains are frozen (`FixedGains`); build "
                                 f"the observer from an `ESODesign` to change "
                                 f"{', '.join(sorted(values))}.")
            schedule = schedule_for(values, d.schedule)
            scales = {k for k in ZHANG38_SCALES if k in values}
            if scales and schedule != "zhang38":
                raise ValueError(
                    f"`{owner}`: {', '.join(sorted(scales))} scale(s) the zhang38 flux "
                    f"schedule; they cannot be set with the {schedule} schedule's "
                    f"parameters ({', '.join(sorted(set(values) - scales))}).")
            merged = {k: getattr(d, k) for k in ("w_rated", "zeta1", "ratio", "w1", "w_min",
                                                 "n2", "n3", *ZHANG38_SCALES)}
            merged.update(values)
            w2 = merged.pop("w2", d.w2)
            zeta2 = merged.pop("zeta2", d.zeta2)
            if schedule == "zhang38":
                merged.update(zeta1=None, ratio=None, w1=None)
            else:  # the scales belong to (38)
                merged.update(dict.fromkeys(ZHANG38_SCALES, 1.0))
            missing = [k for k in SCHEDULE_PARAMS[schedule] if merged.get(k) is None]
            if missing:
                raise ValueError(
                    f"`{owner}`: the {schedule} flux schedule needs "
                    f"{', '.join(missing)} as well.")
            obs = eqx.tree_at(lambda o: o.design, obs,
                              ESODesign(w2, zeta2, schedule, **merged))
        if fal_values:
            obs = obs._with_fal(**fal_values)
        return obs

    def _with_fal(self, **values):
        raise ValueError(f"`{type(self).__name__}.with_design`: only the ESO has fal "
                         f"parameters ({', '.join(values)}).")

    # --- analysis ---------------------------------------------------------------------
    def linear_gains(self, w0, i_dq) -> ESOGains:
        """The gains of zhang2022 (15) at speed `w0` (rad/s) and current `i_dq` (A,
        estimator frame), from the observer's own model."""
        return self.design(self.motor, w0, i_dq)

    def feedback_parameters(self):
        """`(a, eta)` of the feedback f(e) = eta^(1-a) fal(e): `(1, 1)` = linear."""
        return 1.0, 1.0

    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """The error dynamics zhang2022 (11) in the observer's frame convention
        (`error_dynamics`), with the gains evaluated at the operating point as in
        (15)/(37) (the running observer schedules them at its own estimate; the two differ
        by terms proportional to f(e) dG/dw, zero at the designed equilibrium with a
        matched model)."""
        a, eta = self.feedback_parameters()
        gains = self.linear_gains(op.w_m, op.i_dq)
        return error_dynamics(x, op.w_m, op.i_dq, gains, plant, self.motor, a, eta)

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        del plant
        return flux_error_scale(jnp.sqrt(jnp.sum(psi_a(self.motor, op.i_dq) ** 2)), op.w_m)

    def error_state(self, state: FluxObserverState, truth: PlantPoint, plant: PMSMParams):
        return flux_errors(state.psi_ab, state.theta, state.w, truth, plant)

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> FluxObserverState:
        psi, theta, w = flux_estimates(x, truth, plant)
        return FluxObserverState(psi_ab=psi, theta=theta, w=w,
                                 i_prev=jnp.asarray(truth.i_ab, psi.dtype),
                                 started=jnp.asarray(True))

    def init(self, theta0=0.0, w0=0.0) -> FluxObserverState:
        theta0 = jnp.asarray(theta0)
        w0 = jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        zero2 = jnp.zeros(2, dtype)
        return FluxObserverState(
            psi_ab=zero2, theta=wrap_angle(theta0.astype(dtype)), w=w0.astype(dtype),
            i_prev=zero2, started=jnp.asarray(False))

    @abc.abstractmethod
    def _advance(self, state: FluxObserverState, meas: Measurement, T_s):
        """-> (psi_ab, theta, w) at t_k from the state at t_{k-1}."""

    @abc.abstractmethod
    def _w_hat(self, psi_ab, theta, w, i_ab):
        """The speed estimate at t_k."""

    # the step forms its correction at i_{k-1}: the scheduled model is the map's there
    _schedule_current = staticmethod(previous_current_dq)

    def step(self, state: FluxObserverState, meas: Measurement, T_s):
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        psi, theta, w = self._advance(state, meas, T_s)
        psi0 = _flux_init(self.motor, state.theta, meas.i_ab).astype(psi.dtype)
        go = state.started
        psi = jnp.where(go, psi, psi0)
        theta = jnp.where(go, theta, state.theta).astype(state.theta.dtype)
        w = jnp.where(go, w, state.w).astype(state.w.dtype)
        i_k = jnp.asarray(meas.i_ab).astype(state.i_prev.dtype)
        new = FluxObserverState(psi_ab=psi.astype(state.psi_ab.dtype), theta=theta, w=w,
                                i_prev=i_k, started=jnp.ones_like(state.started))
        return new, Estimate(theta_hat=theta, w_hat=self._w_hat(psi, theta, w, i_k),
                             extras={"psi_ab_hat": new.psi_ab})

    def _flux_update(self, state, meas, T_s, G1_f, w_f):
        m = self.motor
        # The correction is held in the estimator frame, which turns at w_f over the
        # interval: its exact integral is T_s sinc(w_f T_s / 2) exp((theta + w_f T_s/2) J).
        half = 0.5 * T_s * w_f
        corr = (T_s * jnp.sinc(half / jnp.pi)) * rotate(G1_f, state.theta + half)
        return (state.psi_ab + T_s * meas.u_ab
                - (0.5 * T_s * m.R_s) * (state.i_prev + meas.i_ab) + corr)


class _AbstractESO(AbstractFluxObserver):
    """(10) with a feedback nonlinearity `feedback(e)`; shared by ESO and LESO."""

    @abc.abstractmethod
    def feedback(self, e):
        """The feedback term f(e) of (10) (V s), element-wise in the estimator frame."""

    def _advance(self, state, meas, T_s):
        e, i_dq = _error(self.motor, state.psi_ab, state.theta, state.i_prev)
        g = self.design(self.motor, state.w, i_dq)
        f = self.feedback(e)
        w_f = state.w + g.g2 @ f
        psi = self._flux_update(state, meas, T_s, g.G1 @ f, w_f)
        theta = wrap_angle(state.theta + T_s * w_f)
        w = state.w + T_s * (g.g3 @ f)
        return psi, theta, w

    def _w_hat(self, psi_ab, theta, w, i_ab):
        del psi_ab, theta, i_ab
        return w

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        """With fal feedback (a < 1), zhang2022's own reduction (`analysis.eso_equilibria`,
        which inverts fal in closed form): the generic route's Gauss-Newton steps can
        oscillate across fal's kinks (its slope jumps at |e| = eta) and then report a
        degenerate point. None for linear feedback (the generic route is used)."""
        a, eta = self.feedback_parameters()
        if isinstance(a, int | float) and float(a) == 1.0:
            return None
        from ..analysis._equilibria import eso_equilibria

        grid = {} if n_grid is None else {"n_grid": n_grid}
        return eso_equilibria(op.w_m, op.i_dq, self.linear_gains(op.w_m, op.i_dq), plant,
                              self.motor, a=a, eta=eta, **grid)

    def fast_classify(self, w_m, i_dq):
        """zhang2022's quartic (34)-(36) in closed form (`analysis.classify_designs`), for
        linear feedback and a pole-placement design with the minimum-norm gains (25)
        (`ESODesign` with the zhang38 or fixed_ratio schedule, n2 = n3 = 0); else None."""
        a, _ = self.feedback_parameters()
        d = self.design
        if not (isinstance(a, int | float) and float(a) == 1.0 and isinstance(d, ESODesign)
                and d.schedule != "fixed_w1" and is_concrete((d.n2, d.n3))
                and float(d.n2) == 0.0 and float(d.n3) == 0.0):
            return None
        from ..analysis._closed_form import _closed_form_classify

        zeta1, w1 = d.zeta1_w1(w_m)
        aw = jnp.abs(w_m)
        ratio = w1 / jnp.where(aw > 0, aw, 1.0)
        m = self.motor
        return _closed_form_classify(w_m, i_dq[..., 0], i_dq[..., 1], zeta1, ratio, d.zeta2,
                                     d.w2, m.L_d, m.L_q, m.psi_f)


class ESOObserver(_AbstractESO):
    r"""Nonlinear extended-state flux observer, zhang2022 (10a)-(10e) with fal (9).

    $$\frac{d\hat\psi}{dt} = u - R_s i - \omega_f J\hat\psi + G_1 f(e),\quad
    \frac{d\hat\theta}{dt} = \hat\omega + g_2 f(e) = \omega_f,\quad
    \frac{d\hat\omega}{dt} = g_3 f(e),$$

    $e = L i - \hat\psi + \psi_f$ (10d)-(10e), $f(e) = \eta^{1-a}\,\mathrm{fal}(e; a,
    \eta)$ element-wise in the estimator frame. fal is the continuous form of (9) (the
    printed linear branch $e/\eta^{a-1}$ is discontinuous; see `fal`); the factor
    $\eta^{1-a}$ is footnote 1's gain scaling, which makes $f'(0) = 1$, so the
    linearisation is (15) with the designed poles for any `a`, `eta`. For $|e| > \eta$
    the feedback grows as $|e|^a$ only: large errors are fed back less than linearly.
    The gains `G1`, `g2`, `g3` come from `design` at the observer's own $\hat\omega$ and
    the measured current in its frame. Returns $\hat\theta$ and $\hat\omega$ (the
    extended state, not the frame speed). Discretisation: see the module docstring.

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`); a different one from the
      plant's is a parameter mismatch.
    - `design`: `ESODesign` (scheduled gains) or `FixedGains`.
    - `a`: fal exponent in (0, 1], default 0.5 (the paper gives no value).
    - `eta`: half-width of fal's linear zone (V s), > 0; default `0.05 * motor.psi_f`
      (about 3 deg of angle error, well above the current-noise level of the flux
      error signal).
    """

    c_emitter: ClassVar[str | None] = "_zhang2022:emit"
    motor: PMSMParams
    design: AbstractGainSchedule
    a: float
    eta: float

    def __init__(self, motor: PMSMParams, design: AbstractGainSchedule, a=0.5, eta=None, *,
                 magnetic=None):
        _check_observer_args("ESOObserver", motor, design)
        self.motor = motor
        self.magnetic = magnetic
        self.design = design
        self.a = a
        self.eta = 0.05 * motor.psi_f if eta is None else eta

    design_units: ClassVar[dict[str, str]] = {**_DESIGN_UNITS, **_FAL_UNITS}

    def __check_init__(self):
        check_design("ESOObserver", a=self.a, eta=self.eta)

    def _fal_parameters(self) -> dict:
        return {"a": self.a, "eta": self.eta}

    def _with_fal(self, **values):
        return self._replace(**values)

    def feedback_parameters(self):
        return self.a, self.eta


    def feedback(self, e):
        r"""$f(e) = \eta^{1-a}\mathrm{fal}(e)$ (V s)."""
        return fal(e, self.a, self.eta) * self.eta ** (1.0 - self.a)


class LESOObserver(_AbstractESO):
    r"""Linear ESO: zhang2022 (10) with fal(e) replaced by e (the "LESO" of Sec. III-A).

    The same as `ESOObserver` with `a = 1` (then $f(e) = e$ exactly). The paper notes
    it is equivalent to the adaptive full-order observer [21]: its frame speed
    $\hat\omega + g_2 e$ is a PI law on $e$; see `AFOObserver`.

    **Arguments:** `motor`, `design` as for `ESOObserver`.
    """

    c_emitter: ClassVar[str | None] = "_zhang2022:emit"
    motor: PMSMParams
    design: AbstractGainSchedule

    def __init__(self, motor: PMSMParams, design: AbstractGainSchedule, *, magnetic=None):
        _check_observer_args("LESOObserver", motor, design)
        self.motor = motor
        self.magnetic = magnetic
        self.design = design


    def feedback(self, e):
        return e


class AFOObserver(AbstractFluxObserver):
    r"""Adaptive full-order observer [21] with the PI speed law (53) of zhang2022.

    Flux: the same model as `ESOObserver` with linear feedback $G_1 e$ (the gain $K$ of
    [21] is (17), scheduled on the integral state $x_I$ of the speed law, the smooth part
    of this observer's $\hat\omega$; see `_advance`). Speed and angle (53):

    $$\hat\omega = -\left(k_p \varepsilon + k_i \int \varepsilon\, dt\right),\qquad
    \frac{d\hat\theta}{dt} = \hat\omega,\qquad k_p = \frac{2\zeta_2\omega_2}{\psi_{ad0}},
    \quad k_i = \frac{\omega_2^2}{\psi_{ad0}},$$

    with $\varepsilon = e_q$, the q-component of the flux error signal (10d) in the
    estimator frame. (53) writes the error as "$\tilde i_d$", the notation of [21],
    whose error current lives in a frame/scaling of its own; here it is derived:
    linearising (10d) about the origin gives $e = \tilde\psi - J\psi_{a0}\tilde\theta$,
    so $e_q = \tilde\psi_q - \psi_{ad0}\tilde\theta$. With $\tilde\omega_I = \omega -
    x_I$ ($x_I$ the integral part), $\dot{\tilde\theta} = \tilde\omega_I + k_p e_q$ and
    $\dot{\tilde\omega}_I = k_i e_q$; for a decoupled flux error this is
    $s^2 + k_p\psi_{ad0} s + k_i\psi_{ad0} = s^2 + 2\zeta_2\omega_2 s + \omega_2^2$.
    The minus sign in $\hat\omega$ is what makes this loop stable with positive $k_p$,
    $k_i$. In the notation of (15) this is the LESO with $g_2 = [0, -k_p]$,
    $g_3 = [0, -k_i]$, another solution of (19) (exactly, for any $\psi_{aq0}$), so the
    linearised error matrix has the same poles as the LESO's. The difference is the
    speed estimate: the AFO returns the PI output (the frame speed, which contains
    $k_p e_q$ and so the measurement noise), the ESO/LESO the integral state.
    `zeta2 = 1` reproduces the paper's $k_p$, $k_i$.

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`).
    - `design`: `ESODesign` (G1 from its flux schedule, $k_p$, $k_i$ from `w2`,
      `zeta2`) or `FixedGains`.
    """

    c_emitter: ClassVar[str | None] = "_zhang2022:emit"
    #: the PI speed law (53) has no null-space components (n2, n3 do not apply)
    design_units: ClassVar[dict[str, str]] = {
        k: v for k, v in _DESIGN_UNITS.items() if k not in ("n2", "n3")}

    motor: PMSMParams
    design: AbstractGainSchedule
    #: the tuner moves the AFO's flux loop along a fixed ratio: measured with the main
    #: job's settings (docs/tuning.md's family table), its design along (38)'s shape is
    #: 14.6 % worse than the paper's in one validation run (the rule allows 10 %), its
    #: fixed-ratio design 5.9 %
    tunable_bounds: ClassVar[dict[str, tuple[float, float, float, str]]] = (
        FIXED_RATIO_BOUNDS)

    def __init__(self, motor: PMSMParams, design: AbstractGainSchedule, *, magnetic=None):
        _check_observer_args("AFOObserver", motor, design)
        self.motor = motor
        self.magnetic = magnetic
        self.design = design


    def linear_gains(self, w0, i_dq) -> ESOGains:
        """The AFO in the notation of zhang2022 (15): G1 from the design, and the PI law
        (53) as $g_2 = [0, -k_p]$, $g_3 = [0, -k_i]$ (see the class docstring)."""
        k_p, k_i = self.design.pi(self.motor, w0, i_dq)
        z = jnp.zeros_like(k_p)
        return ESOGains(G1=self.design(self.motor, w0, i_dq).G1, g2=jnp.stack([z, -k_p]),
                        g3=jnp.stack([z, -k_i]))

    def _pi_output(self, psi_ab, theta, x_I, i_ab):
        e, i_dq = _error(self.motor, psi_ab, theta, i_ab)
        k_p, k_i = self.design.pi(self.motor, x_I, i_dq)
        return x_I - k_p * e[..., 1], e, i_dq, k_i

    def _flux_gain_speed(self, x_I, w_f):
        """The speed the flux gain (17) is scheduled on: the integral state x_I, the smooth
        speed estimate (as k_p, k_i are, and as the ESO/LESO schedule on theirs), not the
        PI output w_f = x_I - k_p e_q. At the end of a fast ramp k_p e_q is large, and a
        G1 scheduled on w_f lost lock for good (stumper's 31,500 rpm/s ramp on a 7 mH
        machine, docs/fast_ramp.md); the linearisation at e = 0 is the same either way."""
        del w_f
        return x_I

    def _advance(self, state, meas, T_s):
        w_f, e, i_dq, k_i = self._pi_output(state.psi_ab, state.theta, state.w,
                                            state.i_prev)
        G1 = self.design(self.motor, self._flux_gain_speed(state.w, w_f), i_dq).G1
        psi = self._flux_update(state, meas, T_s, G1 @ e, w_f)
        theta = wrap_angle(state.theta + T_s * w_f)
        x_I = state.w - T_s * k_i * e[..., 1]
        return psi, theta, x_I

    def _w_hat(self, psi_ab, theta, w, i_ab):
        return self._pi_output(psi_ab, theta, w, i_ab)[0]


def _check_observer_args(owner, motor, design):
    if not isinstance(motor, PMSMParams):
        raise ValueError(
            f"`{owner}(motor=...)` must be a `PMSMParams` (the observer's machine model); "
            f"got {type(motor).__name__}."
        )
    if not isinstance(design, AbstractGainSchedule):
        raise ValueError(
            f"`{owner}(design=...)` must be an `ESODesign` or `FixedGains`; got "
            f"{type(design).__name__}."
        )
