"""The named scenarios of `pmsmjax simulate` (`--scenario NAME`): each builds its
`pmsmjax.Scenario` from the drive, the run's length, the speed and the load (p.u.), with
the sentence that describes it and the rotor's initial speed."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import pmsmjax as pj


@dataclasses.dataclass(frozen=True)
class _ScenarioSpec:
    help: str
    uses_load: bool
    default_load: float
    build: Callable  # (drive, t_end, speed_pu, load_pu) -> (Scenario, description, w_m0)


def _fmt_t(x: float) -> str:
    return f"{x:.4g} s"


def _build_default(drive, T, s, l):
    w, tau = s * float(drive.w_rated), l * float(drive.tau_rated)
    t0, t1, t_on, t_off = T / 30, 11 * T / 30, 8 * T / 15, 4 * T / 5
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.ramp(t0, t1, 0.0, w),
                     tau_L=pj.Profile.steps([t_on, t_off], [tau, 0.0]))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(t0)} to "
            f"{_fmt_t(t1)}, load step 0 -> {l:g} p.u. ({tau:.3g} N m) at {_fmt_t(t_on)} and "
            f"back to 0 at {_fmt_t(t_off)}; {_fmt_t(T)} in all")
    return sc, desc, 0.0


def _build_ramp(drive, T, s, l):
    del l
    w = s * float(drive.w_rated)
    t0, t1 = T / 30, 11 * T / 30
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.ramp(t0, t1, 0.0, w))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(t0)} to "
            f"{_fmt_t(t1)}, no load; {_fmt_t(T)} in all")
    return sc, desc, 0.0


def _build_load_step(drive, T, s, l):
    w, tau = s * float(drive.w_rated), l * float(drive.tau_rated)
    t_on, t_off = T / 3, 2 * T / 3
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.steps([t_on, t_off], [tau, 0.0]))
    desc = (f"constant speed {s:g} p.u. ({w:.1f} rad/s electrical, rotor starting at that "
            f"speed), load step 0 -> {l:g} p.u. ({tau:.3g} N m) at {_fmt_t(t_on)} and back to "
            f"0 at {_fmt_t(t_off)}; {_fmt_t(T)} in all")
    return sc, desc, w


def _build_reversal(drive, T, s, l):
    del l
    w = s * float(drive.w_rated)
    a0, a1, b0, b1 = 0.05 * T, 0.3 * T, 0.5 * T, 0.75 * T
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile([0.0, a0, a1, b0, b1], [0.0, 0.0, w, w, -w]))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(a0)} to "
            f"{_fmt_t(a1)}, reversal to {-s:g} p.u. from {_fmt_t(b0)} to {_fmt_t(b1)}, no "
            f"load; {_fmt_t(T)} in all")
    return sc, desc, 0.0


SCENARIOS: dict[str, _ScenarioSpec] = {
    "default": _ScenarioSpec("speed ramp 0 -> SPEED, then a load step 0 -> LOAD and back "
                             "(event times scale with --t-end)", True, 0.5, _build_default),
    "ramp": _ScenarioSpec("speed ramp 0 -> SPEED, no load", False, 0.0, _build_ramp),
    "load-step": _ScenarioSpec("rotor at SPEED from the start, load step 0 -> LOAD at "
                               "t_end/3, back to 0 at 2 t_end/3", True, 0.5, _build_load_step),
    "reversal": _ScenarioSpec("ramp 0 -> +SPEED, then reversal to -SPEED, no load", False,
                              0.0, _build_reversal),
}
