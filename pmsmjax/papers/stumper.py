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

from .._control._controllers import FOCOutput
from .._control._foc import FOC
from .._data._replay import replay_estimates
from .._frames import angle_error
from .._plant._params import Drive, replace_params
from .._plant._presets import preset
from .._sim._scenario import Profile, Scenario
from .._sim._simulate import simulate
from ..analysis import equilibria_traced
from ..observers import (
    OperatingPoint,
    ParallelModelObserver,
    SensoredObserver,
    d_current_feedforward,
    parallel_model_offset,
    parallel_model_offsets_printed,
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
        pr_L, pr_R = parallel_model_offsets_printed(m, dR, dL, w, jnp.asarray(i_dq))
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


# ---------------------------------------------------------------------------------------
# The tracking filter's lag during a ramp, against (39)
# ---------------------------------------------------------------------------------------

@dataclasses.dataclass
class RampLag:
    """Mean angle lag (deg, true minus estimate) during constant-acceleration ramps,
    measured after 7.5 filter time constants, against stumper (39) (`n_p c / v1` with
    the mechanical acceleration c, i.e. the electrical acceleration over v1).
    `acc_rpm_s`: accelerations (rpm/s); `lag_deg`, `lag39_deg`, `lag_max_deg`."""

    acc_rpm_s: np.ndarray
    lag_deg: np.ndarray
    lag39_deg: np.ndarray
    lag_max_deg: np.ndarray


def ramp_lag(acc_rpm_s=(7875.0, 15750.0, 31500.0), drive: Drive | None = None,
             t_ramp: float = 0.08, **design) -> RampLag:
    """Speed ramps from 300 rpm at each acceleration (rpm/s) with the currents held at
    (0.05, 0.5) p.u. by an encoder-based FOC (speed imposed), replayed through the
    estimator (`design`: its design parameters, default stumper's)."""
    drive = preset("stumper_mt5") if drive is None else drive
    obs = ParallelModelObserver.from_drive(drive, **design)
    Ib = float(drive.base.I_b)
    i_dq = (0.05 * Ib, 0.5 * Ib)
    t0, t1 = 0.01, 0.01 + t_ramp
    out = []
    for a in acc_rpm_s:
        acc = a * RPM
        sc = Scenario(t_end=t1, i_d_ref=Profile.constant(i_dq[0]),
                      i_q_ref=Profile.constant(i_dq[1]),
                      w_m_imposed=Profile.ramp(t0, t1, 300 * RPM, 300 * RPM + acc * t_ramp))
        tr = simulate(drive, FOC.from_drive(drive), SensoredObserver(), sc, T_s=T_S,
                      w_m0=300 * RPM, i_dq0=i_dq)
        est = replay_estimates(obs, tr, theta0=float(tr.theta[0]), w0=float(tr.w_m[0]))
        t = np.asarray(tr.t)
        e = np.degrees(np.asarray(angle_error(tr.theta, est.theta_hat)))
        settled = (t > t0 + 7.5 * 2.0 / float(obs.v2)) & (t < t1)
        out.append((e[settled].mean(), math.degrees(acc / float(obs.v1)),
                    np.abs(e).max()))
    o = np.asarray(out)
    return RampLag(np.asarray(acc_rpm_s, float), o[:, 0], o[:, 1], o[:, 2])


# ---------------------------------------------------------------------------------------
# Closed-loop encoderless FOC: Figs. 3-5
# ---------------------------------------------------------------------------------------

class FeedforwardFOCState(eqx.Module):
    """`FOCState` plus the previous speed reference (rad/s) for the ramp slope."""

    current: object
    speed: object
    w_ref_prev: jnp.ndarray


class FeedforwardFOC(FOC):
    """`FOC` with stumper's d-current feedforward (48), sign corrected
    (`observers.d_current_feedforward`): $i_d^* = i_{d0} - \\tan(\\dot\\omega^*/v_1)
    i_q^*$ with the slope of the speed reference (electrical, from two samples), then
    $i_q^*$ limited to the current limit. `feedforward=False`: the plain FOC. `tau0`
    (N m): the speed integrator's initial value (start in steady state under load).
    Speed mode only. `printed_sign=True`: the printed (48), $+\tan$ (to show the
    erratum)."""

    v1: float = 16000.0
    tau0: float = 0.0
    feedforward: bool = eqx.field(static=True, default=True)
    printed_sign: bool = eqx.field(static=True, default=False)

    def init(self):
        s = FOC.init(self)
        return FeedforwardFOCState(current=s.current, speed=eqx.tree_at(
            lambda x: x.x_I, s.speed, jnp.asarray(self.tau0, float)),
            w_ref_prev=jnp.asarray(jnp.nan))

    def step(self, state, i_dq, w_hat, w_ref, T_s, *, i_ref_override=None,
             speed_mode=True):
        del i_ref_override, speed_mode
        s_state, tau_ref = self.speed.step(state.speed, w_ref, w_hat, T_s)
        i_ref = self.refs(tau_ref, self.current.motor, self.k_tau)
        if self.feedforward:
            prev = state.w_ref_prev
            c = jnp.where(jnp.isnan(prev), 0.0, (w_ref - jnp.where(jnp.isnan(prev), 0.0,
                                                                    prev)) / T_s)
            i_d = d_current_feedforward(i_ref[1], -c if self.printed_sign else c, self.v1,
                                        i_ref[0])
            i_max = self.refs.i_max
            i_d = jnp.clip(i_d, -i_max, i_max)
            q_max = jnp.sqrt(jnp.maximum(i_max ** 2 - i_d ** 2, 0.0))
            i_ref = jnp.stack([i_d, jnp.clip(i_ref[1], -q_max, q_max)])
        c_state, u = self.current.step(state.current, i_ref, i_dq, w_hat, T_s)
        new = FeedforwardFOCState(current=c_state, speed=s_state,
                                  w_ref_prev=jnp.asarray(w_ref, state.w_ref_prev.dtype))
        return new, FOCOutput(u_dq=u, i_ref=i_ref, tau_ref=tau_ref)


def _torque_limit(drive):
    """Torque at the current limit with i_d0 (N m), what the speed loop can ask for."""
    m = drive.three_phase_motor
    i_d0 = 0.05 * float(drive.base.I_b)
    i_q = math.sqrt(float(drive.i_max) ** 2 - i_d0 ** 2)
    return float(drive.k_tau) * float(m.extended_flux(i_d0)) * i_q


#: Fig. 3's load: 95 % of the current-limited torque (the printed 8.8 N m needs 8.3 A)
LOAD_RATED = 0.95 * _torque_limit(preset("stumper_mt5"))
LOAD_HALF = 4.4


def _foc(drive, *, feedforward=False, tau0=0.0, v1=16000.0, printed_sign=False):
    base = FOC.from_drive(drive, alpha_s=2 * math.pi * 10.0,
                          i_d=0.05 * float(drive.base.I_b),
                          tau_max=_torque_limit(drive))
    return FeedforwardFOC(current=base.current, speed=base.speed, refs=base.refs,
                          k_tau=base.k_tau, angle_advance=base.angle_advance,
                          v1=v1, tau0=tau0, feedforward=feedforward,
                          printed_sign=printed_sign)


@dataclasses.dataclass
class ClosedLoop:
    """One encoderless closed-loop run and its numbers (published ones beside them in
    `PUBLISHED`): `traj` (the `Trajectory`), `summary` (dict)."""

    traj: object
    summary: dict


def steady_state(rpm: float, load: float = LOAD_RATED, *, t_end: float = 0.3,
                 L_hat: float | None = 7e-3, drive: Drive | None = None,
                 observer_u_dt=None) -> ClosedLoop:
    """Fig. 3: encoderless speed control at `rpm` under `load` (N m), started in steady
    state; the estimator with the paper's single inductance `L_hat` (H; None: the
    model's L_q). Summary over the last 0.1 s: mean/peak angle error (deg), speed
    ripple (rpm). `observer_u_dt` (V): the dead-time compensation of the estimator's
    voltage when `drive.inverter.u_dt` is set (`simulate`'s argument; 0: the estimator
    takes the voltage commands, as the paper's scheme does)."""
    drive = preset("stumper_mt5") if drive is None else drive
    w = rpm * RPM
    obs = ParallelModelObserver.from_drive(drive, L_hat=L_hat)
    m = drive.three_phase_motor
    i_q0 = load / (float(drive.k_tau) * float(m.extended_flux(0.05 * float(drive.base.I_b))))
    sc = Scenario(t_end=t_end, w_m_ref=Profile.constant(w), tau_L=Profile.constant(load))
    tr = simulate(drive, _foc(drive, tau0=load), obs, sc, T_s=T_S, w_m0=w,
                  i_dq0=(0.05 * float(drive.base.I_b), i_q0), observer_u_dt=observer_u_dt)
    last = np.asarray(tr.t) > t_end - 0.1
    e = np.degrees(np.asarray(tr.theta_err))[last]
    wm = np.asarray(tr.w_m)[last] / RPM
    return ClosedLoop(tr, {"rpm": rpm, "load_Nm": load, "theta_err_mean_deg": -e.mean(),
                           "theta_err_peak_deg": np.abs(e).max(),
                           "speed_ripple_rpm": np.ptp(wm), "ok": bool(tr.ok)})


def acceleration(load: float, *, feedforward: bool, t_end: float = 0.4,
                 L_hat: float | None = 7e-3, drive: Drive | None = None,
                 printed_sign: bool = False) -> ClosedLoop:
    """Figs. 4-5: 300 -> 3000 rpm under `load` (N m) with the speed reference ramped at
    the current-limited acceleration (47) for that load, with or without the
    d-current feedforward. Summary: time from the ramp's start to 3000 rpm within 2 %
    of the step (s), mean acceleration between 10 % and 90 % (rpm/s), peak angle error
    (deg, estimate minus true as the paper plots it), lowest d current (A).
    `printed_sign`: the feedforward with the printed sign of (48)."""
    drive = preset("stumper_mt5") if drive is None else drive
    J = float(drive.mechanics.J)
    acc = (_torque_limit(drive) - load) / J * float(drive.motor.n_p)  # electrical
    w0, w1, t0 = 300 * RPM, 3000 * RPM, 0.02
    t1 = t0 + (w1 - w0) / acc
    obs = ParallelModelObserver.from_drive(drive, L_hat=L_hat)
    m = drive.three_phase_motor
    i_d0 = 0.05 * float(drive.base.I_b)
    i_q0 = load / (float(drive.k_tau) * float(m.extended_flux(i_d0)))
    sc = Scenario(t_end=t_end, w_m_ref=Profile.ramp(t0, t1, w0, w1),
                  tau_L=Profile.constant(load))
    tr = simulate(drive, _foc(drive, feedforward=feedforward, tau0=load,
                              v1=float(obs.v1), printed_sign=printed_sign), obs, sc,
                  T_s=T_S, w_m0=w0,
                  i_dq0=(i_d0, i_q0))
    t = np.asarray(tr.t)
    wm = np.asarray(tr.w_m)
    reach = np.nonzero(wm >= w1 - 0.02 * (w1 - w0))[0]
    t_set = float(t[reach[0]] - t0) if reach.size else float("nan")
    lo, hi = w0 + 0.1 * (w1 - w0), w0 + 0.9 * (w1 - w0)
    ilo, ihi = np.argmax(wm >= lo), np.argmax(wm >= hi)
    slope = 0.8 * (w1 - w0) / RPM / max(t[ihi] - t[ilo], 1e-9)
    e = -np.degrees(np.asarray(tr.theta_err))
    i_ref = np.asarray(tr.i_ref)
    return ClosedLoop(tr, {
        "load_Nm": load, "feedforward": feedforward, "ref_slope_rpm_s": acc / RPM,
        "t_setpoint_s": t_set, "slope_rpm_s": slope,
        "theta_err_max_deg": float(e[np.argmax(np.abs(e))]),
        "i_d_ref_min_A": float(i_ref[:, 0].min()), "ok": bool(tr.ok)})
