"""Parameters of the drive: machine, mechanics, inverter and per-unit bases.

All quantities are SI (Ohm, H, V s, kg m^2, N m s, V, A, rad/s) unless a name says
otherwise. Space vectors are amplitude-invariant (vector length = phase peak value), so
torque is `1.5 n_p (psi x i)` for a three-phase machine. Speeds `w_m` are electrical
(rad/s), `w_M = w_m / n_p` mechanical.

Fields accept Python floats (weakly typed: they adopt the dtype of the simulation, so
float32 runs stay float32) or JAX arrays. To sweep a parameter, replace it by a traced
value inside a vmapped function with `eqx.tree_at`.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._frames import cos_sin
from .._validate import check_finite, check_positive, is_concrete
from ._magnetic import AbstractMagneticModel


class EMFHarmonics(eqx.Module):
    r"""Spatial harmonics of the permanent-magnet flux linkage (and so of the back-EMF).

    The PM flux in the stationary frame is
    $\psi_{pm,ab} = \psi_f e^{\theta J}[1,0]^T + \sum_h \psi_f \frac{a_h}{|h|}
    e^{(h\theta + \phi_h) J}[1,0]^T$, so the back-EMF harmonic of order $h$ has amplitude
    $a_h$ times the fundamental back-EMF at every speed.

    **Arguments:**

    - `order`: signed harmonic orders (static ints). Positive = rotating with the rotor
      (positive sequence, e.g. `7`, `13`), negative = against it (e.g. `-5`, `-11`).
      Order `1`/`0` is not allowed (that is the fundamental / a constant).
    - `amplitude`: back-EMF amplitude of each harmonic relative to the fundamental (-).
    - `phase`: phase of each harmonic at `theta = 0` (rad); default zeros.
    """

    order: tuple[int, ...] = eqx.field(static=True)
    amplitude: jnp.ndarray
    phase: jnp.ndarray

    def __init__(self, order, amplitude, phase=None):
        order = tuple(int(h) for h in np.atleast_1d(order))
        if any(h in (0, 1) for h in order):
            raise ValueError(
                f"`EMFHarmonics(order=...)` must not contain 0 or 1 (the fundamental); "
                f"got {order}."
            )
        self.order = order
        self.amplitude = jnp.asarray(amplitude, dtype=float).reshape(len(order))
        self.phase = (
            jnp.zeros(len(order)) if phase is None
            else jnp.asarray(phase, dtype=float).reshape(len(order))
        )

    def __check_init__(self):
        check_finite("EMFHarmonics", "amplitude", self.amplitude)
        check_finite("EMFHarmonics", "phase", self.phase, "rad")


class PMSMParams(eqx.Module):
    r"""Electrical parameters of a three-phase PMSM with saliency.

    Flux linkage in rotor coordinates: $\psi_{dq} = \mathrm{diag}(L_d, L_q)\,i_{dq} +
    \psi_{pm,dq}(\theta)$, with $\psi_{pm,dq} = [\psi_f, 0]$ without harmonics.

    **Arguments:**

    - `R_s`: stator resistance (Ohm), > 0.
    - `L_d`: d-axis inductance (H), > 0.
    - `L_q`: q-axis inductance (H), > 0.
    - `psi_f`: permanent-magnet flux linkage (V s), >= 0 (0 = synchronous reluctance).
    - `n_p`: number of pole pairs (-), > 0.
    - `harmonics`: optional `EMFHarmonics` of the PM flux (back-EMF spatial harmonics).
    - `magnetic`: optional magnetic model of a saturated machine (`FluxMap`,
      `AlgebraicSaturation`): the plant then takes its flux linkage from
      `magnetic.flux_and_inductance(i_d, i_q)` instead of the constants, which remain the
      machine model the controllers and observers deploy (see `constant_model`). `None`
      (the default): constant inductances, at no extra cost.
    """

    R_s: float
    L_d: float
    L_q: float
    psi_f: float
    n_p: float
    harmonics: EMFHarmonics | None = None
    magnetic: AbstractMagneticModel | None = None

    def __check_init__(self):
        owner = "PMSMParams"
        check_positive(owner, "R_s", self.R_s, "Ohm")
        check_positive(owner, "L_d", self.L_d, "H")
        check_positive(owner, "L_q", self.L_q, "H")
        check_positive(owner, "psi_f", self.psi_f, "V s", allow_zero=True)
        check_positive(owner, "n_p", self.n_p, "pole pairs")

    @property
    def L_dq(self):
        """Inductance matrix diag(L_d, L_q) (H)."""
        return jnp.diag(jnp.stack([jnp.asarray(self.L_d), jnp.asarray(self.L_q)]))

    def extended_flux(self, i_d):
        r"""Extended (active) flux $\psi_{ex} = \psi_f + (L_d - L_q)\,i_d$ (V s) at the
        d-current `i_d` (A): the flux along the d axis whose rotation gives the
        extended back-EMF $\omega\psi_{ex}$ of a salient machine and its torque
        $\tfrac32 n_p \psi_{ex} i_q$. The one place every observer, controller and
        analysis reads it from."""
        return self.psi_f + (self.L_d - self.L_q) * i_d

    @property
    def saturated(self) -> bool:
        """True when the machine has a magnetic model (`magnetic` is not `None`)."""
        return self.magnetic is not None

    def psi_pm_dq(self, theta):
        """PM flux linkage in rotor coordinates at electrical angle `theta` (rad) -> (V s, 2)."""
        psi = jnp.stack([self.psi_f + 0.0 * theta, 0.0 * theta], axis=-1)
        if self.harmonics is None:
            return psi
        for h, a, ph in zip(self.harmonics.order, self.harmonics.amplitude,
                            self.harmonics.phase):
            ang = (h - 1) * theta + ph
            amp = self.psi_f * a / abs(h)
            psi = psi + amp * jnp.stack(cos_sin(ang), axis=-1)
        return psi

    def dpsi_pm_dq_dtheta(self, theta):
        """Derivative of `psi_pm_dq` with respect to `theta` (V s / rad, 2)."""
        d = jnp.zeros(jnp.shape(theta) + (2,), dtype=jnp.result_type(theta, float))
        if self.harmonics is None:
            return d
        for h, a, ph in zip(self.harmonics.order, self.harmonics.amplitude,
                            self.harmonics.phase):
            ang = (h - 1) * theta + ph
            amp = self.psi_f * a / abs(h) * (h - 1)
            d = d + amp * jnp.stack([-jnp.sin(ang), jnp.cos(ang)], axis=-1)
        return d


class DualThreePhaseParams(eqx.Module):
    r"""Dual three-phase PMSM (two star-connected sets shifted by `gamma`) in VSD coordinates.

    After the amplitude-invariant vector-space decomposition the $\alpha\beta$ subspace
    carries the electromechanical energy conversion and behaves like `PMSMParams`
    (`ab`), while the $xy$ subspace is a passive R-L circuit excited only by the PM-flux
    harmonics that map into it (orders $6k \pm 1$, $k$ odd: 5th, 7th, 17th, 19th).
    Torque is $3 n_p (\psi \times i)$ (two sets).

    **Arguments:**

    - `ab`: `PMSMParams` of the $\alpha\beta$ subspace, per three-phase set. Its
      `harmonics` hold all PM-flux harmonics; the plant routes each to its subspace.
    - `L_xy`: inductance of the $xy$ subspace (H), usually the leakage, > 0.
    - `gamma`: angle between the two winding sets (rad), default pi/6.
    """

    ab: PMSMParams
    L_xy: float
    gamma: float = math.pi / 6

    def __check_init__(self):
        check_positive("DualThreePhaseParams", "L_xy", self.L_xy, "H")

    # Delegate the common parameters so a DTP machine can stand in for a 3-phase one.
    @property
    def R_s(self):
        return self.ab.R_s

    @property
    def L_d(self):
        return self.ab.L_d

    @property
    def L_q(self):
        return self.ab.L_q

    @property
    def psi_f(self):
        return self.ab.psi_f

    @property
    def n_p(self):
        return self.ab.n_p

    @property
    def saturated(self) -> bool:
        """True when the alpha-beta subspace has a magnetic model (`ab.magnetic`)."""
        return self.ab.saturated


def _is_dual(motor) -> bool:
    """True when `motor` is a dual three-phase machine (`DualThreePhaseParams`)."""
    return isinstance(motor, DualThreePhaseParams)


def _three_phase(motor) -> PMSMParams:
    """The `PMSMParams` of the torque-producing (alpha-beta) subspace of `motor`."""
    return motor.ab if _is_dual(motor) else motor


def _torque_factor(motor):
    """Torque per unit vector product psi x i: 1.5 n_p (3 n_p for two sets)."""
    return (3.0 if _is_dual(motor) else 1.5) * motor.n_p


class Mechanics(eqx.Module):
    r"""Rigid rotor: $J \dot w_M = \tau_M - B w_M - \tau_L$.

    **Arguments:**

    - `J`: total moment of inertia (kg m^2), > 0.
    - `B`: viscous friction coefficient (N m s/rad), >= 0.
    """

    J: float
    B: float = 0.0

    def __check_init__(self):
        check_positive("Mechanics", "J", self.J, "kg m^2")
        check_positive("Mechanics", "B", self.B, "N m s/rad", allow_zero=True)


class Inverter(eqx.Module):
    """Voltage-source inverter: a ZOH voltage source with a limit and a dead-time error.

    **Arguments:**

    - `u_dc`: DC-link voltage (V), > 0.
    - `u_max`: largest voltage-vector amplitude (V, peak phase). Default `u_dc / sqrt(3)`:
      the linear range of space-vector modulation.
    - `delay`: one-sample computational delay. If `True`, the voltage computed at sample
      k is applied over [t_{k+1}, t_{k+2}).
    - `u_dt`: dead-time and device-drop voltage error per phase (V), >= 0; default `None`
      (an ideal inverter, at no cost). Each phase receives its commanded voltage less
      `u_dt * tanh(i_x / i_dt)` (see `pmsmjax._plant._inverter` for the model).
    - `i_dt`: width of that error's transition around zero phase current (A), >= 0;
      default 0.1 A (a few percent of rated current is typical). `0` is the hard model,
      `u_dt * sign(i_x)`: the smooth model's limit, one parameter for both (hard or smooth
      then follows the inverter everywhere: plant, compensation, replay, identification,
      motor files, generated C); the smooth one keeps the plant differentiable in the
      current and lets `identify` fit `i_dt` (`pmsmjax._plant._inverter`).
    """

    u_dc: float
    u_max: float | None = None
    delay: bool = eqx.field(static=True, default=False)
    u_dt: float | None = None
    i_dt: float = 0.1

    def __check_init__(self):
        check_positive("Inverter", "u_dc", self.u_dc, "V")
        check_positive("Inverter", "u_max", self.u_max, "V")
        check_positive("Inverter", "u_dt", self.u_dt, "V", allow_zero=True)
        check_positive("Inverter", "i_dt", self.i_dt, "A", allow_zero=True)
        if self.u_max is not None and is_concrete((self.u_max, self.u_dc)):
            if np.any(np.asarray(self.u_max) > np.asarray(self.u_dc) * 2 / 3 + 1e-12):
                raise ValueError(
                    f"`Inverter(u_max=...)` (V) cannot exceed the six-step limit "
                    f"2 u_dc / 3 = {2 * float(self.u_dc) / 3:.6g}; got {self.u_max!r}."
                )

    @property
    def u_lim(self):
        """Voltage-vector amplitude limit (V)."""
        return self.u_dc / math.sqrt(3.0) if self.u_max is None else self.u_max

    @property
    def dead_time(self) -> str:
        """The dead-time model, for reports: `"none"` (`u_dt` unset or 0), `"hard"`
        (`u_dt sign(i)`, `i_dt` = 0) or `"smooth"` (`u_dt tanh(i / i_dt)`). Concrete
        values only."""
        if self.u_dt is None or not np.any(np.asarray(self.u_dt) != 0):
            return "none"
        return "hard" if not np.any(np.asarray(self.i_dt) != 0) else "smooth"


class BaseValues(eqx.Module):
    """Per-unit base values (peak-value, amplitude-invariant convention).

    **Arguments:**

    - `U_b`: base voltage (V, peak phase).
    - `I_b`: base current (A, peak).
    - `w_b`: base electrical angular speed (rad/s).
    - `n_p`: pole pairs (-), used for the torque base.

    Derived: `psi_b = U_b / w_b` (V s), `Z_b = U_b / I_b` (Ohm), `L_b = Z_b / w_b` (H),
    `tau_b = 1.5 n_p psi_b I_b` (N m), `t_b = 1 / w_b` (s).
    """

    U_b: float
    I_b: float
    w_b: float
    n_p: float

    def __check_init__(self):
        for name, unit in (("U_b", "V"), ("I_b", "A"), ("w_b", "rad/s"), ("n_p", "-")):
            check_positive("BaseValues", name, getattr(self, name), unit)

    @classmethod
    def from_rated(cls, U_rated_ll: float, I_rated_rms: float, n_rated_rpm: float,
                   n_p: float) -> BaseValues:
        """Bases from rated line-to-line rms voltage (V), rms current (A), speed (rpm)."""
        check_positive("BaseValues.from_rated", "U_rated_ll", U_rated_ll, "V")
        check_positive("BaseValues.from_rated", "I_rated_rms", I_rated_rms, "A")
        check_positive("BaseValues.from_rated", "n_rated_rpm", n_rated_rpm, "rpm")
        return cls(
            U_b=math.sqrt(2.0 / 3.0) * U_rated_ll,
            I_b=math.sqrt(2.0) * I_rated_rms,
            w_b=n_p * 2.0 * math.pi * n_rated_rpm / 60.0,
            n_p=n_p,
        )

    @property
    def psi_b(self):
        return self.U_b / self.w_b

    @property
    def Z_b(self):
        return self.U_b / self.I_b

    @property
    def L_b(self):
        return self.Z_b / self.w_b

    @property
    def tau_b(self):
        return 1.5 * self.n_p * self.psi_b * self.I_b

    @property
    def t_b(self):
        return 1.0 / self.w_b


class Drive(eqx.Module):
    """Everything physical about one drive: machine, mechanics, inverter and ratings.

    **Arguments:**

    - `motor`: `PMSMParams` (three-phase) or `DualThreePhaseParams`.
    - `mechanics`: `Mechanics`.
    - `inverter`: `Inverter`.
    - `base`: `BaseValues` for per-unit scaling and plots.
    - `w_rated`: rated electrical speed (rad/s); "speed in p.u." = fraction of this.
    - `tau_rated`: rated torque (N m); "load in p.u." = fraction of this.
    - `i_max`: current-vector amplitude limit of the controller (A, peak).
    - `name`, `notes`: preset name and the assumptions made (static strings).
    - `T_s`: the drive's sampling period (s), where known (a motor file's `[control]
      T_s`; static): the commands' default period, against which a recording's is
      checked. None: each command's own default.
    """

    motor: PMSMParams | DualThreePhaseParams
    mechanics: Mechanics
    inverter: Inverter
    base: BaseValues
    w_rated: float
    tau_rated: float
    i_max: float
    name: str = eqx.field(static=True, default="custom")
    notes: str = eqx.field(static=True, default="")
    T_s: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.T_s is not None:
            check_positive("Drive", "T_s", self.T_s, "s")
        check_positive("Drive", "w_rated", self.w_rated, "rad/s")
        check_positive("Drive", "tau_rated", self.tau_rated, "N m")
        check_positive("Drive", "i_max", self.i_max, "A")

    @property
    def dual(self) -> bool:
        """True for a dual three-phase machine."""
        return _is_dual(self.motor)

    @property
    def three_phase_motor(self) -> PMSMParams:
        """The `PMSMParams` that describe the torque-producing (alpha-beta) subspace."""
        return _three_phase(self.motor)

    @property
    def k_tau(self):
        """Torque per unit vector product psi x i: 1.5 n_p (3 n_p for two sets)."""
        return _torque_factor(self.motor)


def replace_params(drive: Drive, **values) -> Drive:
    """Return `drive` with motor/mechanics/inverter parameters replaced by name (SI units).

    Names are looked up in `motor` (for a dual three-phase machine: `ab` first, then the
    machine), `mechanics` and `inverter`; e.g. `replace_params(d, L_q=0.0123, J=2e-3)`.
    The new values are validated like the constructor does.
    """
    for name, value in values.items():
        targets = []
        if drive.dual:
            targets += [lambda d: d.motor.ab, lambda d: d.motor]
        else:
            targets += [lambda d: d.motor]
        targets += [lambda d: d.mechanics, lambda d: d.inverter]
        for get in targets:
            obj = get(drive)
            if name in getattr(type(obj), "__dataclass_fields__", {}):
                new = type(obj)(**{**{f: getattr(obj, f) for f in
                                      type(obj).__dataclass_fields__}, name: value})
                drive = eqx.tree_at(get, drive, new)
                break
        else:
            raise ValueError(
                f"Unknown parameter {name!r}; settable names are motor fields "
                f"(R_s, L_d, L_q, psi_f, n_p{', L_xy, gamma' if drive.dual else ''}), "
                f"mechanics (J, B) and inverter (u_dc, u_max, u_dt, i_dt)."
            )
    return drive


def scale_motor(motor, scales: dict):
    """Multiply machine parameters by factors `{name: factor}` (R_s, L_d, L_q, psi_f)."""
    if not scales:
        return motor
    if isinstance(motor, DualThreePhaseParams):
        return eqx.tree_at(lambda m: m.ab, motor, scale_motor(motor.ab, scales))
    names = list(scales)
    return eqx.tree_at(lambda m: [getattr(m, n) for n in names], motor,
                       [getattr(motor, n) * scales[n] for n in names])
