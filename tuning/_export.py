"""Deploying a tuned design: the gains as a lookup table over the speed range.

`gains_table(design, config)` turns a tuned design into the table format of
`pmsmjax.load_gains_table` (see `pmsmjax._gains_table` for the columns, units and the
interpolation rule); `write_report` writes it as `gains.json`, `gains.csv` and `gains.h`.

For a `GainSchedule` the rows are the signed electrical speeds
$s\\,\\omega_r$, $s \\in [-s_{max}, s_{max}]$ in steps of `step_pu` (default 0.025 p.u.),
with $s_{max}$ = 1.25 x the largest speed of the problem (training speeds and schedule
nodes), at least 1.5 p.u.; the design quantities are `GainSchedule.values` there and
$\\omega_1 = \\rho|\\omega_0|$. Between rows the table is linear in speed where the
schedule is linear in the log of its corrections, so an observer built from the table
(`pmsmjax.apply_gains_table`) differs from the tuned one by the interpolation error
only (tested in tests/test_motor_file_and_deploy.py). A `ConstantDesign` is one row of
its physical values.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

import pmsmjax as pj

from ._parametrise import ConstantDesign, GainSchedule
from .scenarios import TuningConfig, make_observer


def table_speeds(config: TuningConfig, step_pu: float = 0.025) -> np.ndarray:
    """The signed electrical speeds (rad/s) of the rows of a scheduled table."""
    s_top = max([abs(float(s)) for s in config.speeds_pu] + list(config.nodes_pu))
    s_max = max(1.5, 1.25 * s_top)
    n_half = int(math.ceil(s_max / step_pu))
    return pj.gains_speed_grid(float(config.drive().w_rated), n_half * step_pu, n_half)


def gains_table(design, config: TuningConfig, *, step_pu: float = 0.025,
                verdict: dict | None = None) -> dict:
    """The gains table (JSON-ready dict, `pmsmjax.load_gains_table` format) of the tuned
    `design` (a `GainSchedule` or a `ConstantDesign`) for the problem `config`: the
    observer's nominal model is the drive's machine. The table carries the sampling
    period `config.T_s`, the objective and `verdict` (the tuner's verdict,
    `{"holds", "baseline", "where_not"}`; None: not recorded, and `gains.h` warns)."""
    drive = config.drive()
    motor = drive.three_phase_motor
    notes = [f"tuned by `python -m tuning` ({config.objective} objective, "
             f"{config.optimiser}) for the {config.observer} observer on drive "
             f"{drive.name}; inductance mismatch range L_hat / L in "
             f"[{config.mismatch[0]:g}, {config.mismatch[1]:g}], speeds "
             f"{', '.join(f'{s:g}' for s in config.speeds_pu)} p.u. of w_rated = "
             f"{float(drive.w_rated):.6g} rad/s"]
    provenance = dict(T_s=float(config.T_s), objective=config.objective, verdict=verdict)
    if isinstance(design, GainSchedule):
        w = table_speeds(config, step_pu)
        v = {k: np.asarray(x, dtype=float)
             for k, x in design.values(jnp.asarray(w / float(design.w_rated))).items()}
        sched = pj.TabulatedDesign(
            w_m=jnp.asarray(w), zeta1=jnp.asarray(v["zeta1"]),
            w1=jnp.asarray(v["ratio"] * np.abs(w)), zeta2=jnp.asarray(v["zeta2"]),
            w2=jnp.asarray(v["w2"]), nu2=jnp.asarray(v["nu2"]), nu3=jnp.asarray(v["nu3"]))
        return pj.gains_table_scheduled(config.observer, sched, motor, drive=drive.name,
                                        notes=notes, **provenance)
    if isinstance(design, ConstantDesign):
        obs = make_observer(config.observer, drive, design)
        units = type(obs).design_units
        values = {n: float(x) for n, x in design.values().items()}
        return pj.gains_table_constant(config.observer, values, dict(units),
                                       drive=drive.name, notes=notes, **provenance)
    raise ValueError(f"`gains_table(design=...)` must be a `GainSchedule` or a "
                     f"`ConstantDesign`; got {type(design).__name__}.")
