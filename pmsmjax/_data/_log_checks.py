"""What a newcomer's log gets wrong, found from the log itself: a time column in the wrong
unit (`sampling_period_warnings`), an encoder offset and voltages logged a sample before
or after they apply (`estimate_encoder_offset`). `pmsmjax convert`, `replay` and
`identify` print the warnings (`recording_warnings`), each saying what to do.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._log_layout import TIME_UNITS
from ._recording import RecordedData


#: A sampling period outside this range (s) is not a drive's: the time unit is probably
#: wrong (warning).
PLAUSIBLE_T_S = (2e-6, 2e-3)
#: An encoder offset estimate above this (deg, electrical) is reported as a warning.
OFFSET_WARN_DEG = 3.0
#: A voltage shift counts as determined when its standard deviation (samples) is below
#: this.
SHIFT_STD_MAX = 0.15


def wrap(x):
    """Angle(s) to [-pi, pi) (NumPy)."""
    return np.remainder(x + np.pi, 2.0 * np.pi) - np.pi


def sampling_period_warnings(T_s: float, unit: str | None = None) -> list[str]:
    """A warning when `T_s` (s) is no drive's sampling period, with the time units that
    would make it one (`unit`: the unit the log's time was read in, if known)."""
    lo, hi = PLAUSIBLE_T_S
    if lo <= T_s <= hi:
        return []
    f0 = TIME_UNITS.get(unit, 1.0)
    better = [f"unit = {u!r} gives T_s = {T_s * f / f0:.3g} s" for u, f in TIME_UNITS.items()
              if lo <= T_s * f / f0 <= hi]
    where = (f"is [time] unit = {unit!r} right?" if unit is not None else
             "was the time column in ms or us? (pmsmjax convert's [time] unit)")
    return [f"T_s = {T_s:.6g} s is not a drive's sampling period (typically 50-500 us): "
            f"{where}" + (f" ({'; '.join(better)})" if better else "")]


class EncoderCheck(NamedTuple):
    """`estimate_encoder_offset`'s result (angles in rad, electrical)."""

    #: the logged angle minus the rotor's (at zero speed where the shift is separable)
    offset: float
    #: by how many samples the voltages lead the machine's (+1: a row logs the voltage
    #: applied one period later, a computational delay the log does not account for);
    #: NaN where the log's speeds cannot tell a shift from an offset
    shift: float
    #: its standard deviation (samples; NaN with the shift)
    shift_std: float
    #: the samples' angle differences about the fit (weighted RMS, rad)
    spread: float
    #: samples used
    n: int


def estimate_encoder_offset(data: RecordedData, motor, *, min_emf: float = 0.2
                            ) -> EncoderCheck:
    """An encoder's offset, and a shift of the voltages, from the voltages, currents and
    the logged angle.

    The stator voltage less the resistive drop and the q inductance's is the extended
    back-EMF d/dt(psi_a e^{j theta}) with psi_a = psi_f + (L_d - L_q) i_d (active flux, on
    the rotor's d axis), so over one period [t_k, t_{k+1}) with the voltage u_k

        e_k = u_k - R_s (i_k + i_{k+1}) / 2 - L_q (i_{k+1} - i_k) / T_s
            = psi_a (e^{j theta_{k+1}} - e^{j theta_k}) / T_s   (psi_a constant over it)
            = j w psi_a sinc-scaled exp(j theta(t_k + T_s / 2)),

    and its direction, less 90 deg times the sign of the speed, is the rotor's angle. The
    logged angle minus that, phi_k, is the encoder's offset plus, for voltages logged s
    samples before they apply, -w_k s T_s: at one speed an offset and a shift look alike;
    they differ in how phi grows with the speed. So phi_k is fitted (weights |e_k|^2, over
    the samples whose |e_k| is at least `min_emf` times the largest) by offset + slope w_k
    where the log's speeds span at least a third of their mean, and by its circular mean
    (the offset alone, shift NaN) where they do not. A shift of whole samples found so is
    undone and the fit repeated, since a shifted voltage meets the resistive and
    inductive drops of another period.

    **Arguments:** `data` with `u_ab` (applied or commanded: a dead-time error lies along
    the current, so it moves the angle little where the back-EMF dominates), `i_ab`,
    `theta` (the logged electrical angle, rad) and `w_m`; `motor` (`PMSMParams`: R_s, L_q).
    """
    data = data.require(("u_ab", "i_ab", "theta", "w_m"))
    chk = _fit_angle(data, motor, min_emf)
    k = round(chk.shift) if math.isfinite(chk.shift) else 0
    if k != 0 and chk.shift_std < SHIFT_STD_MAX and data.n > abs(k) + 2:
        # realign the voltages by the whole shift and fit again: a shifted voltage pairs
        # with the resistive and inductive drops of another period, which biases the
        # first fit's offset (and the fraction of a sample) a little
        u, rest = (data.u_ab[:-k], slice(k, None)) if k > 0 else (data.u_ab[-k:],
                                                                   slice(None, k))
        aligned = RecordedData(t=data.t[rest], u_ab=u, i_ab=data.i_ab[rest],
                               theta=data.theta[rest], w_m=data.w_m[rest])
        fine = _fit_angle(aligned, motor, min_emf)
        chk = fine._replace(shift=k + fine.shift)
    return chk


def _fit_angle(data: RecordedData, motor, min_emf: float) -> EncoderCheck:
    """One fit of phi_k (`estimate_encoder_offset`)."""
    u, i, th, w = data.u_ab, data.i_ab, data.theta, data.w_m
    e = (u[:-1] - float(motor.R_s) * 0.5 * (i[1:] + i[:-1])
         - float(motor.L_q) * (i[1:] - i[:-1]) / data.T_s)
    mag = np.hypot(e[:, 0], e[:, 1])
    th_mid = th[:-1] + 0.5 * wrap(th[1:] - th[:-1])
    w_mid = 0.5 * (w[1:] + w[:-1])
    s = np.sign(w_mid)
    use = (mag >= min_emf * mag.max(initial=0.0)) & (s != 0) & (mag > 0)
    if not np.any(use):
        raise ValueError("estimate_encoder_offset: no sample with a back-EMF (the rotor "
                         "must turn)")
    phi = (th_mid - np.arctan2(e[:, 1], e[:, 0]) + s * (0.5 * np.pi))[use]
    wgt, w_u = mag[use] ** 2 / np.sum(mag[use] ** 2), w_mid[use]
    mean = float(np.angle(np.sum(wgt * np.exp(1j * phi))))
    phi = mean + wrap(phi - mean)  # unwrapped about the circular mean
    w_bar = float(np.sum(wgt * w_u))
    sxx = float(np.sum(wgt * (w_u - w_bar) ** 2))
    if np.ptp(w_u) >= abs(w_bar) / 3.0 and sxx > 0:
        slope = float(np.sum(wgt * (w_u - w_bar) * phi)) / sxx
        offset = float(np.sum(wgt * phi)) - slope * w_bar
        res = phi - offset - slope * w_u
        # weighted least squares: var(slope) = var(res) sum(W^2 (w - w_bar)^2) / sxx^2
        slope_std = math.sqrt(float(np.sum(wgt * res ** 2))
                              * float(np.sum(wgt ** 2 * (w_u - w_bar) ** 2))) / sxx
        shift, shift_std = -slope / data.T_s, slope_std / data.T_s
    else:
        offset, shift, shift_std = mean, math.nan, math.nan
        res = phi - offset
    spread = math.sqrt(float(np.sum(wgt * res ** 2)))
    return EncoderCheck(float(wrap(offset)), shift, shift_std, spread, int(use.sum()))


def encoder_warnings(data: RecordedData, motor, *, layout: bool = False) -> list[str]:
    """Warnings when the recorded angle is offset from the one the voltages show by more
    than `OFFSET_WARN_DEG`, or the voltages are shifted by whole samples
    (`estimate_encoder_offset`); `layout`: say it in `pmsmjax convert`'s terms."""
    if data.theta is None or data.w_m is None or not np.any(data.w_m != 0):
        return []
    try:
        chk = estimate_encoder_offset(data, motor)
    except ValueError:  # no back-EMF in the log
        return []
    out = []
    k = round(chk.shift) if math.isfinite(chk.shift) else 0
    if k != 0 and abs(chk.shift - k) < 0.3 and chk.shift_std < SHIFT_STD_MAX:
        what = (f"{k} period(s) after the row that logs it" if k > 0 else
                f"{-k} period(s) before the row that logs it")
        fix = (f"[voltage] delay = {k} more than the layout has" if layout and k > 0 else
               f"shift the voltages by {k} sample(s) (pmsmjax convert: [voltage] delay)")
        out.append(f"the voltages fit the machine best applied {what} (estimated shift "
                   f"{chk.shift:.2f} +- {chk.shift_std:.2f} samples, from how the angle "
                   f"they show moves with the speed): a computational delay? {fix}")
    deg = math.degrees(chk.offset)
    if abs(deg) > OFFSET_WARN_DEG:
        alike = ("" if math.isfinite(chk.shift) else
                 " (at one speed a voltage delay looks the same: a log over a range of "
                 "speeds tells them apart)")
        out.append(f"the angle looks {deg:+.1f} deg (electrical) ahead of the rotor's "
                   f"according to the voltages{alike}: an encoder offset? Remove it "
                   f"(pmsmjax convert: [angle] offset = \"estimate\", or subtract your own "
                   f"value)")
    return out


def drive_period_warnings(T_s: float, drive) -> list[str]:
    """A warning when a recording's period `T_s` (s) differs from the drive's (`Drive.T_s`,
    a motor file's `[control] T_s`), naming the likely cause."""
    if drive is None or drive.T_s is None or abs(T_s / drive.T_s - 1.0) <= 1e-3:
        return []
    ratio = T_s / drive.T_s
    unit = any(abs(ratio / f - 1.0) < 1e-2 for f in (1e3, 1e-3, 1e6, 1e-6))
    hint = ("" if abs(ratio - 1.0) <= 0.5 else f"; a ratio of {ratio:.4g}: " + (
        "a time column in ms or us?" if unit else
        "a log decimated (every n-th sample) or a drive running at another period?"))
    return [f"the recording's sampling period {T_s:.6g} s differs from the drive's "
            f"[control] T_s = {drive.T_s:.6g} s{hint}"]


def recording_warnings(data: RecordedData, drive, *, inverter=None) -> list[str]:
    """The checks of this module on a recording (`drive`: its machine model), each a
    warning that says what to do; an empty list for a log that passes them all.
    `inverter`: for commanded voltages, the `Inverter` whose dead-time error (`u_dt`,
    `i_dt`) the checks take off them first, over each period at its two ends' currents
    (the error of a few volts along the current otherwise reads as an angle offset or a
    delay where the current has a d component); None takes the voltages as applied."""
    out = sampling_period_warnings(data.T_s) + drive_period_warnings(data.T_s, drive)
    if data.u_ab is not None and data.i_ab is not None and not drive.dual:
        if inverter is not None and inverter.dead_time != "none":
            data = _applied(data, inverter)
        out += encoder_warnings(data, drive.three_phase_motor)
    return out


def _applied(data: RecordedData, inverter) -> RecordedData:
    """`data` with its commanded voltages less the inverter's dead-time error."""
    from .._plant._inverter import observer_voltage

    i = np.asarray(data.i_ab, float)
    u = np.array(data.u_ab, float)
    u[:-1] = np.asarray(observer_voltage(u[:-1], i[:-1], i[1:], float(inverter.u_dt),
                                         inverter.i_dt))
    arrays = {**data.arrays(), "u_ab": u}
    return RecordedData(**arrays, source=data.source)
