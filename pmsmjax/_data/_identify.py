r"""Identification of a drive's parameters from recordings, by least squares through the
differentiable plant.

**Formulation: multiple shooting on the recorded states.** Each recording is cut into
segments of `segment` seconds. A segment starts from the recorded angle at its first
sample and from a current (and, with the mechanics integrated, a speed) that are
unknowns of the fit, starting at the recorded ones, and the plant (`PMSM`, with the
inverter's dead-time error for commanded voltages) is integrated over it, driven by the
recorded voltage and load torque. The residuals are the differences between the
simulated and the measured currents and speeds at the segment's samples, each channel
divided by its noise level. The parameters minimise
their sum of squares (optimistix Levenberg-Marquardt, forward-mode Jacobian: a few
parameters against many residuals).

Why this formulation:

- an *equation-error* fit (regress $u = R i + L\,di/dt + \omega J\psi$) needs the
  derivative of measured currents, which amplifies sensor noise and biases the
  inductances; here no measured signal is differentiated;
- a *simulation-error* fit over the whole recording is the most faithful, but its cost
  surface is rugged (the speed drifts, the angle slips, and the gradients through
  thousands of steps explode or vanish) and every function evaluation is sequential;
- multiple shooting keeps the simulated trajectory close to the measured one (each
  segment restarts from data), so the problem stays nearly quadratic from starting values
  far from the truth, and all segments run side by side under `vmap`. Each segment's
  start is fitted rather than taken from the noisy sample: a start taken from the data
  put the sample's noise into every later sample of the segment (an errors-in-variables
  bias, and standard deviations half the spread over noise seeds for L_q, measured),
  while a fitted start leaves every sample one independent residual. The starts (two
  unknowns per segment, three with the speed, each acting on its own segment only) are
  eliminated by variable projection (`_identify_problem.Problem.projected`), so the
  solver sees only the named parameters and any fitted loads.

**Mechanics: measured or integrated** (`mechanics`). When neither J nor B is fitted
(`"auto"` then picks `"measured"`), the electrical model runs on the recorded rotor
motion, as is usual for electrical parameters: at every sample the model's angle is the
recorded one, its speed the recorded one, and over the sampling period the speed moves
linearly to the next recorded speed (a constant acceleration, integrated exactly by the
RK4 step); only the currents are residuals. This
holds whatever moves the rotor: a dyno that holds the speed, a load that is not logged.
With J or B fitted (`"integrated"`), each segment integrates the mechanics from its
measured start and the speed is a residual too. The load torque that drives it is the
recorded one (`load="recorded"`; zero where none is recorded, with a warning, since a
load the log does not hold runs the model's speed away from the measured one and biases
every parameter) or, for a recording that logs none (`load="auto"`, or for every one with
`"segment"`), a constant load torque per segment fitted with the parameters: unknowns
that enter the mechanics linearly, one per segment (a load that changes within a segment,
as a dyno's does, leaves a residual that the fit warns about). J then shows only through
torque changes within a segment (a current step) and B through speed changes within
one; where a segment has neither, the per-segment load absorbs them and the warnings
say so.

**A model that does not fit.** The current noise the recordings imply is estimated from
the measured currents themselves (`current_noise`: the scaled median absolute second
difference of the currents in rotor coordinates, which a smooth current barely moves and
white noise of standard deviation sigma moves by sqrt(6) sigma), at least a 12-bit
converter's quantisation over +-i_max; a final current residual more than
`max_noise_ratio` (default 3) times it gives an `IdentifiabilityWarning` that says the
values and their standard deviations are not to be trusted and names the usual causes.

**Weights.** A first solve weights the currents by $10^{-3} i_{max}$ and the speed by
$10^{-3}\omega_{rated}$; a second solve, from the first solution, weights each channel
by the RMS of its residual (feasible generalised least squares), so a noisy channel does
not dominate a clean one. The standard deviations are the Gauss-Newton ones,
$\mathrm{cov} = s^2 (J^TJ)^{-1}$ with $s^2$ the residual variance per degree of
freedom, mapped to SI units; `condition` is the 2-norm condition number of the Jacobian
with unit-norm columns (1 for perfectly separable parameters; above about $10^6$ two or
more parameters act alike on this recording).

**Identifiability.** A parameter that does not change the residuals (a zero Jacobian
column: the recording cannot see it) raises `IdentifyError` naming it and saying what
excitation it needs; one that is only weakly determined (relative standard deviation
above `warn_rel_std`) or nearly collinear with another (correlation above 0.995) gives an
`IdentifiabilityWarning` with the same explanation, and the result lists it in
`warnings`. Parameters are fitted in log space (positive), `u_dt` linearly (it may be 0);
`i_dt` in log space, so from the smooth dead-time model (`i_dt = 0`, the hard one, is no
start): phase currents that never come within a few `i_dt` of zero leave its column dead
or weak, and the error or warning names it with the excitation it needs.

**Saturation.** `fit` with `"saturation"` (or some of `a_d0, a_dd, a_q0, a_qq, a_dq,
i_f`) fits an `AlgebraicSaturation` with its exponents held: the plant's
`PMSMParams.magnetic` is that model, built from the traced coefficients. The segments
are integrated in the plant's flux-linkage form (`_identify_saturation.flux_rates`:
the model's current is explicit in the flux, so no Newton inversion per evaluation;
tested equal to `PMSM` with the model to fourth order in the step): each segment starts
from the flux of its measured current (the model's Newton inversion, differentiated
through). The recordings' current ranges are checked (`ExcitationWarning`) and the
flux uncertainty over them is reported (`_identify_saturation`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._plant._params import Drive
from .._sim._integrate import RK4, check_drive_step
from . import _identify_saturation as _sat
from ._identifiable import IDENTIFIABLE as IDENTIFIABLE, SATURATION_FIT
from ._identify_motion import (
    IdentifyError,
    current_noise,
    cut,
    load_mode,
    mechanics_mode,
    recorded_speed,
)
from ._identify_problem import (
    MECH as _MECH,
    MOTOR as _MOTOR,
    Problem as _Problem,
    final as _final,
    solve as _solve,
)
from ._recording import RecordedData


class IdentifiabilityWarning(UserWarning):
    """A fitted parameter is only weakly determined by the recording(s)."""


class ExcitationWarning(IdentifiabilityWarning):
    """The recordings do not excite the currents a saturation model needs: the recorded
    d- or q-axis current covers too little of the drive's current range (the message
    names the axis, the range recorded and the range needed, and the coefficients left
    to extrapolation)."""


class IdentifyResult(eqx.Module):
    """Result of `identify`.

    - `drive`: the drive with the fitted parameters replaced.
    - `parameters`: `{name: {"value", "initial", "std", "unit"}}` in SI units.
    - `residual_rms`: RMS of the final residuals per channel: `{"i_A": ..., "w_rad_s": ...}`.
    - `cost`: final weighted sum of squares / degrees of freedom (about 1 after the
      reweighting).
    - `condition`: condition number of the column-normalised Jacobian.
    - `correlation`: the parameters' correlation matrix (`names` order).
    - `names`: the fitted parameters, in order.
    - `n_residuals`, `n_segments`, `segment_s`, `steps`: problem size and solver steps.
    - `warnings`: the identifiability warnings (also issued as `IdentifiabilityWarning`,
      or `ExcitationWarning` for a recording that does not excite a saturation model).
    - `saturation`: `None` unless a saturation model was fitted; then `{"model"`: the
      fitted `AlgebraicSaturation` (also `drive`'s magnetic model), `"currents"`: the
      recorded current ranges (A) and the fractions of the needed ranges they cover,
      `"flux_std"`: the 1-sigma flux uncertainty over those currents (V s, and relative
      to the PM flux)`}`.
    - `traces`: per recording, `{"t", "i_ab", "i_model", "w_m", "w_model"}` (NumPy): the
      measured signals and the segment-wise model response at the fitted parameters
      (each segment restarts the model at the logged angle and its fitted start).
    - `mechanics`: `"measured"` (the model ran on the recorded angle and speed; the speed
      residual is not part of the fit and reported as 0) or `"integrated"`.
    - `noise`: `{"i_A": ...}`, the current noise the recordings imply (`current_noise`).
    - `loads`: per recording, `None` (its load torque was the recorded one, or none acted
      on the model) or `{"t_start"` (s, each segment's start), `"value"` (N m, the fitted
      constant load torque of each segment, added to a logged one), `"std"` (N m)`}`.
    """

    drive: Drive
    parameters: dict
    residual_rms: dict
    cost: float
    condition: float
    correlation: np.ndarray
    names: tuple
    n_residuals: int
    n_segments: int
    segment_s: float
    steps: int
    warnings: tuple
    traces: list
    saturation: dict | None = None
    mechanics: str = "integrated"
    noise: dict | None = None
    loads: list | None = None


def _recordings(data) -> list[RecordedData]:
    recs = [data] if isinstance(data, RecordedData) else list(data)
    if not recs:
        raise IdentifyError("`identify(data=...)` needs at least one recording.")
    for k, r in enumerate(recs):
        if not isinstance(r, RecordedData):
            raise IdentifyError(f"`identify(data=...)` item {k} must be a `RecordedData` "
                                f"(pmsmjax.load_recording); got {type(r).__name__}.")
        missing = [n for n in ("u_ab", "i_ab", "theta") if getattr(r, n) is None]
        if missing:
            raise IdentifyError(
                f"recording {k}{' (' + r.source + ')' if r.source else ''} lacks "
                f"{', '.join(missing)}: identification needs the voltage, the current and "
                f"the rotor angle (an encoder or resolver log); it has "
                f"{', '.join(r.names)}.")
    return recs


def identify(drive: Drive, data: RecordedData | Sequence[RecordedData],
             fit: Sequence[str] = ("R_s", "L_d", "L_q", "psi_f"), *,
             voltage: str = "applied", segment: float = 0.02, n_substeps: int = 1,
             max_steps: int = 100, rtol: float = 1e-10, atol: float = 1e-10,
             warn_rel_std: float = 0.01, saturation=None, exponents=None,
             min_coverage: float = 0.5, mechanics: str = "auto", load: str = "auto",
             max_noise_ratio: float = 3.0) -> IdentifyResult:
    """Fit the parameters `fit` of `drive` to one or more recordings (module docstring).

    **Arguments:**

    - `drive`: the drive (three-phase) whose parameters are the starting values; the
      others are held.
    - `data`: a `RecordedData` or a sequence of them, each with `t`, `u_ab`, `i_ab`,
      `theta` (rad, electrical), and `w_m` (rad/s; else derived from `theta`) and
      `tau_L` (N m; else zero) where recorded.
    - `fit`: names among `IDENTIFIABLE`: R_s (Ohm), L_d, L_q (H), psi_f (V s), J
      (kg m^2), B (N m s/rad), u_dt (V), i_dt (A), and the coefficients of an `AlgebraicSaturation`
      (a_d0, a_dd, a_q0, a_qq, a_dq, i_f; `"saturation"` stands for all six): the plant
      then saturates (`PMSMParams.magnetic`), L_d, L_q, psi_f cannot be fitted with them
      (they are then only the deployed constants: the fitted drive takes the model's
      small-current values), and the recordings' current ranges are checked
      (`min_coverage`).
    - `voltage`: `"applied"` (the recorded `u_ab` reached the windings) or `"commanded"`
      (the controller's voltage: the plant applies the inverter's dead-time error,
      `drive.inverter.u_dt`, hard or smooth as its `i_dt` says, fitted when `u_dt`, `i_dt`
      are in `fit`).
    - `segment`: multiple-shooting segment length (s).
    - `n_substeps`: RK4 steps per sampling period.
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt limits and tolerances.
    - `warn_rel_std`: relative standard deviation above which a parameter is reported as
      weakly determined.
    - `saturation`: the starting `AlgebraicSaturation` of a saturation fit; default: the
      drive's magnetic model if it is one, else one whose small-current values are the
      drive's L_d, L_q, psi_f (`_identify_saturation.default_start`).
    - `exponents`: `(S, T, U, V)` (-, held) of the fitted model; default: the starting
      model's, or 4, 2, 2, 2.
    - `mechanics`: `"measured"` (the model runs on the recorded angle and speed: any
      speed profile, a dyno's included, and no load torque needed), `"integrated"` (the
      mechanics integrated over each segment with the recorded load torque; needed to
      fit J or B), or `"auto"` (default): `"integrated"` when J or B is fitted, else
      `"measured"` (module docstring).
    - `load`: the load torque of integrated mechanics: `"recorded"` (the log's `tau_L`,
      zero where none is logged), `"segment"` (a constant load torque per segment fitted
      with the parameters, on top of a logged one), or `"auto"` (default): fitted per
      segment for a recording that logs none. Not with mechanics `"measured"`.
    - `max_noise_ratio`: the final current residual above this multiple of the current
      noise the recordings imply gives a warning that the model does not fit them.
    - `min_coverage`: the fraction of the current range (i_d over [-i_max, 0], |i_q| up
      to i_max) the recordings must cover in each axis for a saturation fit; below it an
      `ExcitationWarning` names the axis and the coefficients left undetermined.

    **Returns:** an `IdentifyResult`. Raises `IdentifyError` (a `ValueError`) for unusable
    data or a parameter the data cannot determine.
    """
    if not isinstance(drive, Drive):
        raise IdentifyError(f"`identify(drive=...)` must be a `pmsmjax.Drive`; got "
                            f"{type(drive).__name__}.")
    if drive.dual:
        raise IdentifyError(f"`identify` fits three-phase drives; {drive.name!r} is dual "
                            f"three-phase.")
    names = _sat.expand([fit] if isinstance(fit, str) else fit)
    bad = [n for n in names if n not in IDENTIFIABLE]
    if not names or bad:
        raise IdentifyError(f"`identify(fit=...)`: {', '.join(map(repr, bad)) or 'nothing'} "
                            f"is not a parameter it can fit; choose among "
                            f"{', '.join(IDENTIFIABLE)} or 'saturation'.")
    sat_fit = any(n in SATURATION_FIT for n in names)
    constants = [n for n in names if n in ("L_d", "L_q", "psi_f")]
    if sat_fit and constants:
        raise IdentifyError(
            f"`identify(fit=...)` has {', '.join(constants)} with saturation coefficients: "
            f"with a saturation model the plant's flux comes from the model, and L_d, L_q, "
            f"psi_f are only the constants the drive deploys (the fitted drive takes the "
            f"model's small-current values); leave them out of fit.")
    if sat_fit and drive.three_phase_motor.harmonics is not None:
        raise IdentifyError(
            f"`identify(fit=...)` with saturation coefficients models a sinusoidal "
            f"machine; {drive.name!r} has back-EMF harmonics (orders "
            f"{tuple(drive.three_phase_motor.harmonics.order)}): remove them from the "
            f"motor file (the [motor.harmonics] table) for the saturation fit.")
    if not 0.0 <= min_coverage <= 1.0:
        raise IdentifyError(f"`identify(min_coverage=...)` (-) must lie in [0, 1]; got "
                            f"{min_coverage!r}.")
    try:
        start_sat = _sat.start_model(drive, saturation, exponents) if sat_fit else None
    except ValueError as e:
        raise IdentifyError(str(e)) from None
    if voltage not in ("applied", "commanded"):
        raise IdentifyError(f"`identify(voltage=...)` must be 'applied' or 'commanded'; got "
                            f"{voltage!r}.")
    for n in ("u_dt", "i_dt"):
        if n in names and voltage != "commanded":
            raise IdentifyError(
                f"{n} ({IDENTIFIABLE[n][0]}): with voltage='applied' the recorded voltage "
                f"already reached the windings, so the inverter error cannot act on the "
                f"model; fit {n} from commanded voltages (voltage='commanded').")
    if "i_dt" in names and "u_dt" not in names and drive.inverter.dead_time == "none":
        raise IdentifyError("i_dt (A) shapes the dead-time error, and the drive has none "
                            "(u_dt unset or 0): set u_dt (--set u_dt=V) or fit it too.")
    mechanics = mechanics_mode(names, mechanics)
    if not max_noise_ratio > 0:
        raise IdentifyError(f"`identify(max_noise_ratio=...)` (-) must be > 0; got "
                            f"{max_noise_ratio!r}.")
    if not (segment > 0 and math.isfinite(segment)):
        raise IdentifyError(f"`identify(segment=...)` (s) must be > 0; got {segment!r}.")
    recs = _recordings(data)
    fit_load = load_mode(recs, mechanics, load)
    segs = []
    for k, r in enumerate(recs):
        check_drive_step(drive, r.T_s, RK4(), n_substeps)
        m = max(2, int(round(segment / r.T_s)))
        if r.n - 1 < 2 * m:
            raise IdentifyError(
                f"recording {k}{' (' + r.source + ')' if r.source else ''} is too short: "
                f"{r.n} samples ({(r.n - 1) * r.T_s:.4g} s) for segments of {m} samples "
                f"({segment:g} s); it needs at least two segments (record longer or pass "
                f"a shorter `segment`).")
        segs.append(cut(r, m))
        if mechanics == "integrated" and r.tau_L is None and not fit_load[k]:
            warnings.warn(
                f"recording {k}{' (' + r.source + ')' if r.source else ''} has no load "
                f"torque: with mechanics='integrated' (J or B fitted) the model's rotor "
                f"runs with none, so under a load or on a dyno its speed leaves the "
                f"recorded one and every parameter is biased. Log the load torque, fit "
                f"one per segment (load='segment'), or fit the electrical parameters alone "
                f"(mechanics='measured').",
                IdentifiabilityWarning, stacklevel=2)

    sat_info, excite = None, []
    if sat_fit:
        sat_info, excite = _sat.coverage(recs, float(drive.i_max), min_coverage)
        for msg in excite:
            warnings.warn(msg, ExcitationWarning, stacklevel=2)
    p0 = []
    lin = []
    for n in names:
        if n in SATURATION_FIT:
            v = getattr(start_sat, n)
        elif n in _MOTOR:
            v = getattr(drive.motor, n)
        elif n in _MECH:
            v = getattr(drive.mechanics, n)
        else:
            v = getattr(drive.inverter, n)
        v = 0.0 if v is None else float(v)
        if n != "u_dt" and not v > 0:
            raise IdentifyError(f"the starting value of {n} ({IDENTIFIABLE[n][0]}) must be "
                                f"> 0 to fit it in log space; got {v!r} (set it with "
                                f"--set {n}=VALUE" + ("; i_dt = 0 is the hard dead time, "
                                "and fitting i_dt fits the smooth one" if n == "i_dt"
                                else "") + ").")
        p0.append(v)
        lin.append(max(v, 1.0) if n == "u_dt" else 0.0)
    problem = _Problem(drive=drive, names=names, p0=jnp.asarray(p0), lin_scale=jnp.asarray(lin),
                       commanded=voltage == "commanded", n_substeps=n_substeps,
                       saturation=start_sat, measured=mechanics == "measured",
                       n_seg=tuple(s.w0.shape[0] for s in segs), fit_load=fit_load,
                       load_scale=float(drive.tau_rated), i_scale=1e-2 * float(drive.i_max),
                       w_scale=1e-2 * float(drive.w_rated))
    k_named = len(names)
    x = jnp.zeros(problem.n_unknowns())
    sig_i = 1e-3 * float(drive.i_max)
    sig_w = 1e-3 * float(drive.w_rated)
    steps = 0
    for stage in range(2):
        # the weights as arrays: both stages run one program (as Python floats they would
        # be static values: a compile per stage)
        args = (segs, jnp.asarray(sig_i, x.dtype), jnp.asarray(sig_w, x.dtype))
        x, result, n_steps, rms_i, rms_w = _solve(problem, x, args, rtol, atol, max_steps)
        steps += int(n_steps)
        if result != optx.RESULTS.successful and stage == 1:
            warnings.warn(f"identify: the Levenberg-Marquardt solve stopped without meeting "
                          f"its tolerances ({optx.RESULTS[result]}); the values may not be "
                          f"converged (raise max_steps).", IdentifiabilityWarning, stacklevel=2)
        if stage == 0:  # reweight each channel by its residual RMS (floored)
            _check_finite(float(rms_i), float(rms_w))
            sig_i = max(float(rms_i), 1e-9 * float(drive.i_max))
            sig_w = max(float(rms_w), 1e-9 * float(drive.w_rated))
    # `args` of the last stage: its weights are the final ones (only stage 0 reweights)
    r, Jx, rms_i, rms_w, model = _final(problem, x, args)
    rms_i, rms_w = float(rms_i), float(rms_w)
    _check_finite(rms_i, rms_w)
    r, Jx = np.asarray(r), np.asarray(Jx)
    dof = max(r.size - x.size - problem.n_start * sum(problem.n_seg), 1)
    s2 = float(r @ r) / dof
    col = np.maximum(np.linalg.norm(Jx, axis=0), 1e-300)
    warn_list = []
    dead = [n for n, c in zip(names, col) if not c > 1e-10 * col.max()]
    if dead:
        raise IdentifyError(
            "the recording(s) cannot determine " + "; ".join(
                f"{n} ({IDENTIFIABLE[n][0]}): it does not change the model's response; it "
                f"needs {IDENTIFIABLE[n][1]}" for n in dead) + ". Leave it out of --fit or "
            "record such excitation.")
    Jn = Jx / col
    sv = np.linalg.svd(Jn, compute_uv=False)
    condition = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    cov_n = s2 * np.linalg.pinv(Jn.T @ Jn)
    cov_x = cov_n / np.outer(col, col)
    std_x = np.sqrt(np.maximum(np.diag(cov_x), 0.0))
    d = np.sqrt(np.maximum(np.diag(cov_n), 1e-300))
    corr = (cov_n / np.outer(d, d))[:k_named, :k_named]
    loads = [None if ld is None else {
        "t_start": np.asarray(rec.t)[np.arange(s.w0.shape[0]) * s.w_meas.shape[1]],
        "value": problem.load_scale * np.asarray(x[ld]),
        "std": problem.load_scale * std_x[ld]}
        for rec, s, ld in zip(recs, segs, problem.slices())]
    vals = {k: float(v) for k, v in problem.values(x).items()}
    params = {}
    for k, n in enumerate(names):
        v = vals[n]
        std = float(problem.lin_scale[k]) * std_x[k] if n == "u_dt" else abs(v) * std_x[k]
        params[n] = {"value": v, "initial": p0[k], "std": float(std),
                     "unit": IDENTIFIABLE[n][0]}
        rel = std / abs(v) if v != 0 else math.inf
        if n == "u_dt":  # judged against the error's size relative to the data's voltage
            rel = std / max(abs(v), 0.05)
        if not rel <= warn_rel_std:
            warn_list.append(
                f"{n} ({IDENTIFIABLE[n][0]}) is weakly determined: {v:.6g} +- {std:.3g} "
                f"(1 sigma, {100 * rel:.3g} %); the recording(s) need more "
                f"{IDENTIFIABLE[n][1]}.")
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            if abs(corr[a, b]) > 0.995:
                warn_list.append(
                    f"{names[a]} and {names[b]} act almost alike on this recording "
                    f"(correlation {corr[a, b]:+.4f}): their individual values are uncertain; "
                    f"{names[a]} needs {IDENTIFIABLE[names[a]][1]}, {names[b]} needs "
                    f"{IDENTIFIABLE[names[b]][1]}.")
    noise_i = current_noise(recs)
    # no real drive's current is cleaner than a 12-bit converter over +-i_max quantises it
    floor_i = 2.0 * float(drive.i_max) / 4096 / math.sqrt(12.0)
    if rms_i > max_noise_ratio * max(noise_i, floor_i):
        causes = (["a load torque the log does not hold (fit without J and B to run the "
                   "model on the recorded speed, or log tau_L)"]
                  if mechanics == "integrated" and not all(fit_load) else
                  ["a load torque that changes within a segment, as a dyno's does (shorter "
                   "segments, or fit without J and B to run the model on the recorded "
                   "speed)"] if mechanics == "integrated" else [])
        if voltage == "applied":
            causes.append("commanded voltages taken as applied (voltage='commanded')")
        causes += ["a delay between the logged voltage and current",
                   "a wrong sampling period or angle offset"]
        warn_list.append(
            f"the model does not fit the recording(s): the current residual ({rms_i:.3g} A "
            f"RMS) is {rms_i / max(noise_i, floor_i):.3g} times the current noise they show "
            f"({noise_i:.3g} A, from the sample-to-sample variation; at least {floor_i:.2g} "
            f"A, a 12-bit converter's over +-i_max), so the values and their standard "
            f"deviations are not to be trusted. Usual causes: " + "; ".join(causes) + ".")
    for msg in warn_list:
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=2)
    try:
        fitted = _fitted_drive(drive, {n: v for n, v in vals.items() if n not in SATURATION_FIT})
    except ValueError as e:  # a value no drive can have: the model does not fit the data
        raise IdentifyError(
            f"the fit ended at values no drive can have ({e}): the model does not fit the "
            f"recording(s) (residual RMS {rms_i:.3g} A"
            + ("" if mechanics == "measured" else f", {rms_w:.3g} rad/s")
            + "). Check what the log holds: commanded or applied voltages (voltage=), a "
            "load torque that is not logged (fit the electrical parameters alone, "
            "mechanics='measured'), the sampling period and the angle's offset.") from None
    if sat_fit:
        fitted = _sat.fitted_drive(fitted, _sat.with_values(start_sat, vals))
        sat_info = {"model": fitted.three_phase_motor.magnetic, "currents": sat_info,
                    "flux_std": _sat.flux_uncertainty(
                        problem.magnetic, x, cov_x, sat_info,
                        float(fitted.three_phase_motor.psi_f))}
    traces = []
    for rec, s, (i_m, w_m) in zip(recs, segs, model):  # at the final x (stage 1)
        n_seg, m = s.w_meas.shape
        k = np.arange(1, n_seg * m + 1)
        traces.append({"t": np.asarray(rec.t)[k], "i_ab": np.asarray(rec.i_ab)[k],
                       "i_model": np.asarray(i_m).reshape(-1, 2), "w_m": recorded_speed(rec)[k],
                       "w_model": np.asarray(w_m).reshape(-1)})
    return IdentifyResult(
        drive=fitted, parameters=params, residual_rms={"i_A": rms_i, "w_rad_s": rms_w},
        cost=s2, condition=condition, correlation=corr, names=names,
        n_residuals=int(r.size), n_segments=int(sum(s.w0.shape[0] for s in segs)),
        segment_s=float(segment), steps=steps, warnings=tuple(excite + warn_list), traces=traces,
        saturation=sat_info, mechanics=mechanics, noise={"i_A": noise_i}, loads=loads)


def _check_finite(rms_i: float, rms_w: float) -> None:
    if not (math.isfinite(rms_i) and math.isfinite(rms_w)):
        raise IdentifyError(
            "the fit diverged (non-finite model response): the starting values are too far "
            "from the recording's drive, or T_s is too coarse for the plant (try "
            "n_substeps > 1).")


def _fitted_drive(drive: Drive, vals: dict) -> Drive:
    """`drive` with the fitted values, validated like a user's `replace_params`."""
    from .._plant._params import replace_params

    return replace_params(drive, **vals)
