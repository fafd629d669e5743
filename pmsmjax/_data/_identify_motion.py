"""What the rotor and the sensors of a recording give identification (`_identify`): the
rotor's motion in the model (`mechanics_mode`, `motion_step`: measured or integrated) and
the current noise the recordings imply (`current_noise`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from .._frames import park
from ._recording import RecordedData


class IdentifyError(ValueError):
    """A fitted parameter the recording(s) cannot determine, or unusable data."""



def mechanics_mode(names: Sequence[str], mechanics: str = "auto") -> str:
    """The rotor motion `identify` uses for the fitted `names`: `"measured"` or
    `"integrated"` (`mechanics` "auto": integrated when J or B is fitted)."""
    mech_fit = [n for n in names if n in ("J", "B")]
    if mechanics not in ("auto", "measured", "integrated"):
        raise IdentifyError(f"`identify(mechanics=...)` must be 'auto', 'measured' or "
                            f"'integrated'; got {mechanics!r}.")
    if mechanics == "measured" and mech_fit:
        raise IdentifyError(
            f"`identify(mechanics='measured')` runs the model on the recorded speed, so "
            f"{', '.join(mech_fit)} cannot act on it; fit them with "
            f"mechanics='integrated' (or 'auto') and a logged load torque.")
    if mechanics == "auto":
        return "integrated" if mech_fit else "measured"
    return mechanics



def motion_step(field, y, args, theta, w_m, acc, measured: bool):
    """One step's `(state, vector field, its args)`: unchanged when the rotor's
    mechanics are integrated; when it moves as `measured`, the state (any module with
    `theta`, `w_m`) takes the recorded angle (rad) and speed (rad/s) and the field turns
    it at the constant acceleration `acc` (rad/s^2) instead of the mechanical equation."""
    if not measured:
        return y, field, args

    def moved(t, v, a):
        rates = field(t, v, a)
        return eqx.tree_at(lambda r: r.w_m, rates, acc + 0.0 * rates.w_m)

    y = eqx.tree_at(lambda v: (v.theta, v.w_m), y, (theta, w_m))
    return y, moved, eqx.tree_at(lambda a: a.free, args, 0.0)



def current_noise(recs: Sequence[RecordedData]) -> float:
    """The current noise (A, one standard deviation per component) the recordings imply:
    1.4826 x the median absolute second difference of the measured currents in rotor
    coordinates (recorded angle), over sqrt(6). White noise of standard deviation sigma
    gives sigma; a current that is smooth over three samples adds little, and steps are
    outliers the median ignores."""
    d2 = []
    for r in recs:
        i_dq = np.asarray(park(np.asarray(r.i_ab, float), np.asarray(r.theta, float)))
        d2.append((i_dq[2:] - 2.0 * i_dq[1:-1] + i_dq[:-2]).ravel())
    d2 = np.concatenate(d2)
    return float(1.4826 * np.median(np.abs(d2)) / math.sqrt(6.0))
