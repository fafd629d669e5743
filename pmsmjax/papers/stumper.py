r"""The experiments of stumper (Figs. 1, 3-5 and the ramp lag (39)) as named simulations.

J.-F. Stumper, D. Paulus, R. Kennel, "A Nonlinear Estimator for Dynamical and Robust
Sensorless Control of Permanent Magnet Synchronous Machines".

The estimator is `ParallelModelObserver` (registered as `"parallel-model"`); the
closed forms, corrections and discretisation are documented in its module. Everything
the paper does not state is an assumption and is named here:

- machine: `preset("stumper_mt5")` (Table I; inertia J = 2e-3 kg m^2 assumed, which makes
  the current-limited no-load acceleration (47) 31,950 rpm/s, the paper's 31,500 rpm/s);
  Fig. 1 uses the isotropic 7 mH machine of its caption (`fig1_drive`);
- sampling 16 kHz (`T_s = 62.5e-6` s), no computational delay, no inverter
  non-linearity, no current noise; FOC with current bandwidth 2 pi 500 rad/s (the paper's
  closed current loop of about 1 ms, Sec. IV-C) and speed bandwidth 2 pi 10 rad/s
  (assumed); current limit 6.3 A peak, i_d0 = 0.05 p.u. = 0.315 A (the paper: 0.3 A);
- the paper's "rated load 8.8 N m" needs 8.3 A with K = 0.236 V s, more than the 6.3 A
  limit (6.69 N m at 6.3 A): Fig. 3's load is taken as 95 % of the current-limited torque
  (`LOAD_RATED`, 6.36 N m) and "half load" as 4.4 N m as printed.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._control import FOC, FOCOutput, FOCState
from .._frames import angle_error
from .._params import Drive, preset, replace_params
from .._replay import replay_estimates
from .._scenario import Profile, Scenario
from .._simulate import simulate
from ..analysis import equilibria_traced
from ..observers import OperatingPoint, ParallelModelObserver, SensoredObserver
from ..observers._parallel_model import (
    d_current_feedforward,
    parallel_model_offset,
    printed_offsets,
)


T_S = 62.5e-6
#: electrical rad/s per rpm for the 3 pole pairs of the MT5
RPM = 3 * 2 * math.pi / 60
#: Fig. 1 operating point: 300 rpm, (i_d, i_q) = (0.05, 0.5) p.u.
FIG1_RPM, FIG1_I_DQ_PU = 300.0, (0.05, 0.5)
#: Fig. 1 ranges: dR in [-0.86, 2.6] Ohm, dL in [-7, 14] mH (estimate minus true)
FIG1_DR, FIG1_DL = (-0.86, 2.6), (-7e-3, 14e-3)

#: Numbers printed in stumper Sec. VI (angles in deg, times in s, currents in A).
PUBLISHED = {
    "fig3": {"theta_err_deg": 7.0, "note": "offset about 7 deg at 100 and 3000 rpm, "
                                           "rated load; proportional to the load"},
    "fig4": {"t_setpoint_s": 0.230, "theta_err_max_deg": 10.0,
             "note": "300 -> 3000 rpm at half load (4.4 N m), at the current limit"},
    "fig5": {"t_setpoint_s": 0.150, "slope_rpm_s": 31500.0, "theta_err_max_deg": 20.0,
             "i_d_ff_A": -2.25, "speedup_pct": 17.0,
             "note": "300 -> 3000 rpm without load, with the d-current feedforward"},
    "ramp": {"v1": 16000.0, "v2": 253.0, "lag_limit_deg": 20.0},
}


def fig1_drive() -> Drive:
    """The isotropic 7 mH machine of Fig. 1's caption (stumper_mt5 otherwise)."""
    return replace_params(preset("stumper_mt5"), L_d=7e-3, L_q=7e-3)


# ---------------------------------------------------------------------------------------
# Fig. 1: sensitivity to resistance and inductance errors
# ---------------------------------------------------------------------------------------

@dataclasses.dataclass
class Sensitivity:
    """Steady-state angle offsets (deg, estimate minus true, stumper (21)) against a
    resistance error `dR` (Ohm) or an inductance error `dL` (H), estimate minus true.

    Per axis (`"R"`, `"L"`): `x` (the error grid), `formula_open` (current given in
    rotor coordinates, `parallel_model_offset(frame="rotor")`), `simulated_open` (the
    estimator replayed over a simulated sensored record with that current), `printed`
    (stumper (32) resp. (31) as printed), `formula_closed` (current held in the
    estimated frame, `frame="estimated"`), `equilibria` (the stable equilibrium of
    the generic analysis, `pmsmjax.analysis`), `simulated_closed` (sensorless closed
    current loop, at `x_closed`).
    """

    rpm: float
    i_dq: tuple
    axes: dict


def _fig1_point(drive):
    Ib = float(drive.base.I_b)
    return FIG1_RPM * RPM, (FIG1_I_DQ_PU[0] * Ib, FIG1_I_DQ_PU[1] * Ib)


def _model(motor, dR, dL):
    f = lambda v: jnp.asarray(v, float)  # noqa: E731  (traced leaves: no recompiles)
    return eqx.tree_at(lambda m: (m.R_s, m.L_d, m.L_q), motor,
                       (f(motor.R_s + dR), f(motor.L_d + dL), f(motor.L_q + dL)))


def _steady_record(drive, w, i_dq, observer, t_end):
    sc = Scenario(t_end=t_end, w_m_imposed=Profile.constant(w),
                  i_d_ref=Profile.constant(i_dq[0]), i_q_ref=Profile.constant(i_dq[1]))
    return simulate(drive, FOC.from_drive(drive), observer, sc, T_s=T_S, w_m0=w,
                    i_dq0=i_dq)


def sensitivity(n: int = 9, n_closed: int = 3, drive: Drive | None = None,
                t_end: float = 0.1, equilibria_method: str = "auto") -> Sensitivity:
    """Fig. 1 by three routes (see `Sensitivity`): `n` points per axis for the formulas,
    the open-loop replay and the equilibria (`equilibria_method`: "auto", the
    estimator's closed-form route, or "generic", the root search of
    `pmsmjax.analysis`, much slower to compile), `n_closed` closed-loop runs per axis;
    records of `t_end` s, offsets averaged over the last 10 ms."""
    drive = fig1_drive() if drive is None else drive
    m = drive.three_phase_motor
    w, i_dq = _fig1_point(drive)
    last = int(round(0.01 / T_S))
    obs0 = ParallelModelObserver.from_drive(drive)
    # open loop: the encoder holds the current at i_dq in rotor coordinates
    rec = _steady_record(drive, w, i_dq, SensoredObserver(), t_end)
    th0, w0 = float(rec.theta[0]), float(rec.w_m[0])
    i_rot = jnp.asarray(rec.i_dq)[-last:].mean(0)

    @jax.jit
    def open_loop(dR, dL):
        est = replay_estimates(obs0.with_motor(_model(m, dR, dL)), rec, theta0=th0, w0=w0)
        return -jnp.mean(angle_error(rec.theta, est.theta_hat)[-last:])

    op = OperatingPoint(jnp.asarray(w), jnp.asarray(i_dq))

    @jax.jit
    def equilibrium(dR, dL):
        eq = equilibria_traced(obs0.with_motor(_model(m, dR, dL)), m, op,
                               method=equilibria_method)
        k = jnp.argmin(jnp.where(eq.stable, jnp.abs(eq.theta), jnp.inf))
        return -eq.theta[k], jnp.sum(eq.stable)

    def closed_loop(dR, dL):
        tr = _steady_record(drive, w, i_dq, obs0.with_motor(_model(m, dR, dL)), t_end)
        return -float(np.mean(np.asarray(tr.theta_err)[-last:]))

    axes = {}
    for name, (lo, hi) in (("R", FIG1_DR), ("L", FIG1_DL)):
        x = np.linspace(lo, hi, n)
        xc = np.linspace(lo, hi, n_closed)
        z = np.zeros_like(x)
        dR, dL = (x, z) if name == "R" else (z, x)
        dRc, dLc = (xc, 0 * xc) if name == "R" else (0 * xc, xc)
        sim = jax.vmap(open_loop)(jnp.asarray(dR), jnp.asarray(dL))
        eq, n_stable = jax.vmap(equilibrium)(jnp.asarray(dR), jnp.asarray(dL))
        pr_L, pr_R = printed_offsets(m, dR, dL, w, jnp.asarray(i_dq))
        deg = lambda a: np.degrees(np.asarray(a))  # noqa: E731
        axes[name] = dict(
            x=x, x_closed=xc,
            formula_open=deg(parallel_model_offset(m, dR, dL, w, i_rot, frame="rotor")),
            simulated_open=deg(sim),
            printed=deg(pr_R if name == "R" else pr_L),
            formula_closed=deg(parallel_model_offset(m, dR, dL, w, jnp.asarray(i_dq),
                                                     frame="estimated")),
            equilibria=deg(eq), n_stable=np.asarray(n_stable),
            simulated_closed=np.degrees([closed_loop(a, b) for a, b in zip(dRc, dLc)]),
        )
    return Sensitivity(rpm=FIG1_RPM, i_dq=FIG1_I_DQ_PU, axes=axes)
