r"""The observer contract: what every position/speed estimator provides to the library.

**Timing** (the same for the closed loop and for offline replay): at sampling instant
$t_k$ an observer receives a `Measurement` with the currents sampled at $t_k$ and the
stator voltage that was applied over the previous period $[t_{k-1}, t_k)$ (zero at
$k = 0$). It returns the `Estimate` valid at $t_k$ and its state for the next instant.
Everything it needs from the past (e.g. $i_{k-1}$ for an integration rule) lives in its
state, so the step is a pure function of `(state, measurement, T_s)`.

**Analysis** (what `pmsmjax.analysis` is generic over). Each observer states once

- its own machine model, the field `motor` (`PMSMParams`): observer-model mismatch in any
  parameter ($R_s$, $L_d$, $L_q$, $\psi_f$) is replacing it (`with_motor`);
- its continuous-time *error dynamics* $\dot x = f(x; \mathrm{op}, \mathrm{plant})$ at an
  `OperatingPoint` (constant electrical speed $\omega_0$ and constant current $i_0$ held
  by the current controller in the observer's estimated frame), in coordinates in which
  that operating point is an equilibrium: `error_rhs`. The coordinates are named in
  `coordinates` (`ErrorCoordinates`: names, units, which one is the angle error
  $\tilde\theta = \theta - \hat\theta$, true minus estimate); `error_scale` gives the
  size of each coordinate at the operating point (so that $x/\text{scale}$ is O(1));
- the two maps between its discrete state and those coordinates at a true plant state
  (`error_state`, `observer_state`), through which the library checks that the
  continuous model is the observer that runs (`pmsmjax.analysis.discrete_error_map`:
  the Jacobian of one real `step` is $I + T_sA + O(T_s^2)$);
- its design: `design_parameters()` (name -> value, SI), `with_design(**values)`, the
  units in `design_units`, and `from_drive(drive, **design)`, the papers' default design
  for any drive (used by the registry, `make_observer`);
- the names and units of its observer-specific outputs, `extras` (e.g. an estimated
  flux or back-EMF), which it returns in `Estimate.extras` and which `simulate` and
  `replay` carry through under the same names.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._frames import park, wrap_angle
from .._plant._magnetic import AbstractMagneticModel, apparent_model
from .._plant._params import PMSMParams
from .._plant._recheck import recheck


class Measurement(eqx.Module):
    """What an observer sees at one sampling instant.

    - `i_ab`: stator current sampled at t_k, stationary frame (A, shape (2,)).
    - `u_ab`: stator voltage applied over [t_{k-1}, t_k), stationary frame (V, (2,)).
    - `theta`: encoder angle at t_k (rad, electrical); NaN when no encoder is present.
      Only sensored observers may use it.
    - `w_m`: encoder speed at t_k (rad/s, electrical); NaN when absent.
    """

    i_ab: jnp.ndarray
    u_ab: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray


class Estimate(eqx.Module):
    """Observer output at one sampling instant.

    - `theta_hat`: estimated electrical rotor angle, wrapped to (-pi, pi] (rad).
    - `w_hat`: estimated electrical speed (rad/s).
    - `extras`: observer-specific estimates by name (the observer class lists them, with
      their units, in its `extras` class attribute), e.g. `psi_ab_hat` (V s, the
      zhang2022 observers' stator flux). Empty for observers without any.
    """

    theta_hat: jnp.ndarray
    w_hat: jnp.ndarray
    extras: dict = eqx.field(default_factory=dict)


class OperatingPoint(eqx.Module):
    """A constant-speed, constant-current operating point of the plant.

    - `w_m`: electrical rotor speed (rad/s), constant.
    - `i_dq`: the current held by the current controller in the observer's estimated
      frame (A, `(2,)`): in rotor coordinates the current is $e^{-\\tilde\\theta J} i_{dq}$.
    - `theta`: the true electrical rotor angle at this instant (rad), or None (default).
      Only observers whose error dynamics depend on the rotor angle itself (not just on
      the errors, e.g. gains applied per stationary-frame component) read it: with
      `theta` they return the instantaneous error dynamics, without it their average
      over one electrical period (what the generic equilibria and stability analysis
      then use); `analysis.floquet` treats the periodic dynamics exactly. Every other
      observer ignores it.
    """

    w_m: jnp.ndarray
    i_dq: jnp.ndarray
    theta: jnp.ndarray | None = None

    def __init__(self, w_m, i_dq=(0.0, 0.0), theta=None):
        self.w_m = jnp.asarray(w_m)
        self.i_dq = jnp.asarray(i_dq, dtype=jnp.result_type(self.w_m, float))
        self.theta = None if theta is None else jnp.asarray(theta, self.i_dq.dtype)


class PlantPoint(eqx.Module):
    """The true plant at one sampling instant (for `error_state` / `observer_state`).

    - `theta`: electrical rotor angle (rad); `w_m`: electrical speed (rad/s);
    - `i_ab`: stator current, stationary frame (A, `(2,)`).
    """

    theta: jnp.ndarray
    w_m: jnp.ndarray
    i_ab: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class ErrorCoordinates:
    """Names and units of an observer's error coordinates (static metadata).

    - `names`: one name per coordinate, e.g. `("psi_d", "psi_q", "theta", "w")`.
    - `units`: their SI units, e.g. `("V s", "V s", "rad", "rad/s")`.
    - `angle`: index of the angle error $\\tilde\\theta$ (rad, true minus estimate).
    - `doc`: what each coordinate is (one line each).
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    angle: int
    doc: tuple[str, ...] = ()

    def __post_init__(self):
        if len(self.names) != len(self.units) or not 0 <= self.angle < len(self.names):
            raise ValueError("`ErrorCoordinates`: `names` and `units` must have the same "
                             "length and `angle` must index one of them.")
        if self.units[self.angle] != "rad":
            raise ValueError("`ErrorCoordinates`: the angle coordinate must be in rad.")

    @property
    def n(self) -> int:
        return len(self.names)


class AbstractObserver(eqx.Module):
    """Base class of every observer (see the module docstring for the contract).

    Subclasses implement `init`, `step`, `from_drive`, `with_design`, `error_rhs`,
    `error_scale`, `error_state` and `observer_state` (and `design_parameters` where the
    design is not the fields named in `design_units`), and declare the class attributes
    `coordinates`, `design_units` and `extras`.
    """

    motor: eqx.AbstractVar[PMSMParams]
    #: The current-scheduled model (`with_magnetic`): None (default) runs the constant
    #: model `motor`; a magnetic model makes every step use the apparent inductances and
    #: PM flux of that model at the measured current (see `scheduled_at`).
    magnetic: AbstractMagneticModel | None = eqx.field(default=None, kw_only=True)
    #: Error coordinates of `error_rhs` (names, units, angle index).
    coordinates: ClassVar[ErrorCoordinates]
    #: Design parameters: name -> unit and meaning.
    design_units: ClassVar[dict[str, str]] = {}
    #: Observer-specific outputs in `Estimate.extras`: name -> unit and meaning.
    extras: ClassVar[dict[str, str]] = {}
    #: Tunable design (the `tuning` package): design parameter -> default `(lo, hi)`
    #: bounds as factors on its value in `from_drive`'s design (0 < lo < 1 < hi; the
    #: value must be > 0). Empty: the observer declares no tunable design.
    tunable: ClassVar[dict[str, tuple[float, float]]] = {}
    #: How the tuner derives the bounds of a `tunable` parameter from the drive
    #: (`tuning.DesignSpace`): name -> `"tracking"` (a type-2 angle-tracking bandwidth,
    #: rad/s), `"damping"` (its damping ratio), `"estimator"` (an estimator bandwidth,
    #: rad/s), `"explicit"` (the rate of a feedback applied once per sampling period,
    #: 1/s) or `"time"` (a filter time constant, s). A tunable name not listed keeps the
    #: `tunable` factor box around its default.
    tunable_kinds: ClassVar[dict[str, str]] = {}
    #: Tunable design parameters whose bounds are physical constants of the observer, not
    #: derived from the drive: name -> `(lo, hi, start, why)`: the bounds, the value that
    #: stands for the paper's design (a scheduled parameter has no single value) and the
    #: reason, in the parameter's unit.
    tunable_bounds: ClassVar[dict[str, tuple[float, float, float, str]]] = {}
    #: Coordinates the tuner searches instead of some `tunable` parameters (a
    #: reparametrisation in physical terms): name -> `(unit, kind)` with a kind of
    #: `tunable_kinds`; `tuning_replaces` names the parameters they stand for, and
    #: `design_from_tuning` / `tuning_from_design` map between the two (traceable).
    tuning_coordinates: ClassVar[dict[str, tuple[str, str]]] = {}
    tuning_replaces: ClassVar[tuple[str, ...]] = ()
    #: Whether the tuner narrows each coordinate's bounds to the interval around the
    #: paper's design in which the linearised error dynamics are stable over the drive's
    #: operating points (`tuning.DesignSpace`), for a design whose stable region is
    #: narrower than its rules give (morawiec2023's).
    tuning_spectral: ClassVar[bool] = False
    #: Whether the error dynamics (`error_rhs`, and the step in error coordinates)
    #: depend on the rotor angle (`OperatingPoint.theta`). False: they are rotation
    #: invariant, and the angle-resolved analyses (`analysis.harmonic_ripple`,
    #: `analysis.input_matrix`) evaluate them at one angle.
    angle_dependent: ClassVar[bool] = False
    #: Whether `analysis.equilibria` searches the error dynamics' second branch by
    #: default (`n_starts = n_grid` Newton starts on the full system; module docstring of
    #: `pmsmjax.analysis._generic`): for an observer whose inner problem shows two
    #: branches at ordinary operating points, where the default solve would report them
    #: degenerate. A caller's `n_starts` wins.
    equilibria_starts: ClassVar[bool] = False
    #: Gauss-Newton steps of `analysis.equilibria`'s inner solve per angle of its grid
    #: (`n_gauss_newton`; module docstring of `pmsmjax.analysis._generic`). One step is
    #: exact where the error dynamics are affine in the other coordinates at a fixed
    #: angle; an observer that is not (e.g. a gain scheduled on the speed estimate, one
    #: of those coordinates) declares more, or the solve leaves most grid points
    #: unsettled and the point without a verdict. A caller's `n_gauss_newton` wins.
    equilibria_gauss_newton: ClassVar[int] = 3
    #: The speed (p.u. of rated) below which the observer's design does not claim to hold
    #: the angle: the tuner's low-speed rule sets apart the validation runs that take a
    #: sensored drive slower than this (`tuning.TuningProblem.low_speed_limit_pu`,
    #: `tuning.low_speed_runs`). 0: no limit declared, every run is judged.
    low_speed_limit_pu: ClassVar[float] = 0.0
    #: The preset of the observer's paper's drive (`pmsmjax.preset` name): the machine
    #: the tuner, the benchmarks and the docs figures run it on by default. None: no
    #: paper drive (e.g. the sensored pass-through); such an observer runs on `zhang750`.
    paper_motor: ClassVar[str | None] = None
    #: The sampling period (s) of that paper drive; None: the preset's own default.
    paper_T_s: ClassVar[float | None] = None
    #: Its C emitter, `"module:function"` inside `pmsmjax.firmware` (e.g.
    #: `"_stumper:emit"`), a function `(observer, T_s) -> CObserver` that writes this
    #: class's step in C. Read from the class itself, never inherited (a subclass may
    #: change the step): a class without its own has no C code, and `export_c` says so.
    c_emitter: ClassVar[str | None] = None

    def __check_init__(self):
        if self.magnetic is not None and not isinstance(self.magnetic,
                                                        AbstractMagneticModel):
            raise ValueError(
                f"`{type(self).__name__}(magnetic=...)` must be None (the constant model) "
                f"or an `AbstractMagneticModel` (e.g. `pj.FluxMap`); got "
                f"{type(self.magnetic).__name__}.")

    # --- the current-scheduled model ----------------------------------------------
    def with_magnetic(self, magnetic: AbstractMagneticModel | None):
        r"""A copy that schedules its machine model on the measured current: at every
        step its `motor`'s $L_d$, $L_q$, $\psi_f$ become `magnetic`'s apparent values
        (`AbstractMagneticModel.apparent_inductance`) at the current measured in the
        observer's estimated frame, so that its model flux $\psi_f + L_d i_d$,
        $L_q i_q$ equals the map's $\psi_{dq}(i)$ at that current. `None` returns to the
        constant model (the default). $R_s$, the design and the gains fixed at
        construction are kept. See docs/observers.md for what each observer's equations
        make of it."""
        if magnetic is not None and not isinstance(magnetic, AbstractMagneticModel):
            raise ValueError(
                f"`{type(self).__name__}.with_magnetic(magnetic=...)` must be None (the "
                f"constant model) or an `AbstractMagneticModel` (e.g. `pj.FluxMap`); got "
                f"{type(magnetic).__name__}.")
        return eqx.tree_at(lambda o: o.magnetic, self, magnetic,
                           is_leaf=lambda x: x is None)

    def scheduled_at(self, i_dq):
        """This observer with its `motor`'s `L_d`, `L_q`, `psi_f` replaced by the apparent
        values of `magnetic` at the current `i_dq` (A, `(2,)`, estimated frame); itself
        when `magnetic` is None."""
        if self.magnetic is None:
            return self
        return eqx.tree_at(lambda o: o.motor, self,
                           apparent_model(self.motor, self.magnetic, i_dq))

    def _schedule_current(self, state, meas):
        """The current (A, estimated frame) the scheduled model is evaluated at in a step
        from `state` with `meas`: by default the measured current in the frame of the
        state's angle estimate. Observers whose model error is formed at another sample
        override it."""
        return park(jnp.asarray(meas.i_ab), state.theta)

    def _scheduled(self, state, meas):
        """The observer whose model a step from `state` with `meas` uses (itself for the
        constant model: the default step is unchanged)."""
        if self.magnetic is None:
            return self
        return self.scheduled_at(self._schedule_current(state, meas))

    # --- running ------------------------------------------------------------------
    @abc.abstractmethod
    def init(self, theta0=0.0, w0=0.0):
        """The state at k = 0, with initial angle estimate `theta0` (rad) and speed
        estimate `w0` (rad/s)."""

    @abc.abstractmethod
    def step(self, state, meas: Measurement, T_s) -> tuple[object, Estimate]:
        """`(state at t_{k-1}, measurement at t_k, T_s (s)) -> (state at t_k, Estimate)`."""

    def check_values(self, T_s) -> None:
        """Raise `ValueError`, naming the argument, for a concrete value this observer
        cannot run with at the sampling period `T_s` (s). `simulate` and `replay` call it
        before they compile a run, which traces the observer's Python floats
        (`pmsmjax._sim._batching.values_as_arrays`), so that checks made inside `step` no
        longer see them. Default: the construction checks of the observer and every
        module in it (which `with_design` and `with_motor` skip); an observer with a
        bound on `T_s` adds it."""
        recheck(self)

    # --- design ---------------------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def from_drive(cls, drive, *, motor: PMSMParams | None = None, **design):
        """The paper's default design for `drive` (any preset); `motor` replaces the
        observer's machine model (default: the drive's), `design` overrides design
        parameters by name (see `design_units`)."""

    def design_parameters(self) -> dict:
        """The current design as `{name: value}` (SI units as in `design_units`). Default:
        the fields named in `design_units`; an observer whose design lives elsewhere (a
        gain schedule, a PLL module) overrides it."""
        return {k: getattr(self, k) for k in self.design_units}

    @classmethod
    def design_from_tuning(cls, coords: dict, drive=None) -> dict:
        """The design parameters (`tuning_replaces`) of tuning coordinates `coords`
        (`tuning_coordinates` names; values may be traced) on `drive` (the `Drive` whose
        constants a coordinate may be scaled with). None declared: identity."""
        return dict(coords)

    @classmethod
    def tuning_from_design(cls, design: dict, drive=None) -> dict:
        """The tuning coordinates of the design parameters `design` on `drive` (the
        inverse of `design_from_tuning`)."""
        return dict(design)

    @abc.abstractmethod
    def with_design(self, **values):
        """A copy with the named design parameters replaced (values may be traced, so
        that `vmap` over a grid of designs works)."""

    def _check_design_names(self, values: dict, owner: str | None = None) -> None:
        """`ValueError` naming the unknown design parameters among `values` and the ones
        this class has (`design_units`); `owner` names the calling function."""
        owner = owner or f"{type(self).__name__}.with_design"
        bad = sorted(set(values) - set(self.design_units))
        if bad:
            raise ValueError(
                f"`{owner}`: unknown design parameter(s) {', '.join(bad)}; "
                f"{type(self).__name__} has {', '.join(self.design_units)}.")

    def _replace(self, **values):
        """A copy with the named fields replaced (no checks; values may be traced)."""
        return eqx.tree_at(lambda o: [getattr(o, k) for k in values], self,
                           list(values.values()))

    def with_motor(self, motor: PMSMParams):
        """A copy whose machine model is `motor` (observer-model mismatch)."""
        if not isinstance(motor, PMSMParams):
            raise ValueError(f"`with_motor(motor=...)` must be a `PMSMParams`; got "
                             f"{type(motor).__name__}.")
        return eqx.tree_at(lambda o: o.motor, self, motor)

    # --- analysis -----------------------------------------------------------------
    @abc.abstractmethod
    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """$dx/dt$ of the error dynamics at operating point `op` for the true machine
        `plant` (the observer's own model is `self.motor`); `x` in `coordinates`."""

    @abc.abstractmethod
    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        """Positive size of each error coordinate at `op` (same units), `(n,)`."""

    @abc.abstractmethod
    def error_state(self, state, truth: PlantPoint, plant: PMSMParams):
        """Error coordinates of the observer `state` (at t_k, after its step) against
        the true plant state `truth` at t_k."""

    @abc.abstractmethod
    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams):
        """The observer state at t_k (as after a step) whose error coordinates against
        `truth` are `x`: the inverse of `error_state`."""

    def designed_error(self, op: OperatingPoint, plant: PMSMParams):
        """The designed equilibrium of `error_rhs` at `op` (in `coordinates`): the
        origin (the default), or, for an observer with a deliberate steady-state error
        (e.g. the phase lag of a low-pass back-EMF observer), that point. The contract
        tests and `analysis.linearization`'s default start from it."""
        del plant
        return jnp.zeros(self.coordinates.n, jnp.result_type(op.w_m, float))

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        """The equilibria by a family-specific route (`analysis.Equilibria`), where the
        family has one that is preferable to the generic route, else None (the
        default). `analysis.equilibria(method="auto")` uses it. `n_grid`: the route's
        search grid where it has one (None: its default; the tuner passes its own)."""
        del plant, op, n_grid
        return None

    def fast_classify(self, w_m, i_dq):
        """A closed-form classification of the equilibria with a matched model
        (`analysis.DesignClass`), where the family has one, else None (the default). It
        must agree with the generic route; `analysis.classify` uses it when allowed."""
        del w_m, i_dq
        return None


class SensoredObserver(AbstractObserver):
    """Passes the encoder angle and speed through (sensored control).

    The state is empty; `init`'s arguments are ignored. It has no estimation-error
    dynamics, so the analysis functions do not apply to it (they raise `ValueError`).

    **Arguments:** `motor`: the drive's machine model (only carried along; default None
    stands for "not needed").
    """

    motor: PMSMParams | None = None
    coordinates: ClassVar[ErrorCoordinates] = ErrorCoordinates(("theta",), ("rad",), 0)

    def init(self, theta0=0.0, w0=0.0):
        del theta0, w0
        return ()

    def step(self, state, meas: Measurement, T_s):
        del T_s
        return state, Estimate(theta_hat=wrap_angle(meas.theta), w_hat=meas.w_m)

    @classmethod
    def from_drive(cls, drive, *, motor=None, **design):
        if design:
            raise ValueError(f"`SensoredObserver` has no design parameters; got "
                             f"{', '.join(sorted(design))}.")
        return cls(drive.three_phase_motor if motor is None else motor)

    def design_parameters(self) -> dict:
        return {}

    def with_design(self, **values):
        if values:
            raise ValueError("`SensoredObserver` has no design parameters.")
        return self

    def _no_analysis(self, *args):
        raise ValueError("The sensored observer reads the encoder: it has no estimation-"
                         "error dynamics to analyse. Choose a sensorless observer.")

    error_rhs = error_scale = error_state = observer_state = _no_analysis
