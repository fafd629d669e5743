r"""The tuning problem: what is tuned, on which drive, against which runs, judged how.

`TuningProblem` is built once (from the command line or the API), checked on
construction, and never changed: every later stage takes the pieces it needs from it
(the drive, the observer family, the scenario settings, the objective settings, the
search budget) and hands its own result to the next stage:

    problem -> scenarios -> design space -> objective -> search -> report

Defaults follow the observer's paper: the drive its class names (`paper_motor`,
`pmsmjax.observers.paper_drive`) and that motor's sampling period (`sampling_period`),
unless `motor` / `motor_file` / `T_s` are given.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os

import pmsmjax as pj
from pmsmjax.observers import (
    DEFAULT_PAPER_DRIVE,
    observer_class,
    observer_names,
    paper_drive,
)


#: Sampling period (s) of the presets that are no registered observer's paper drive: the
#: saturated 3.5 kW IPMSM runs on morawiec2023's drive.
OTHER_T_S = {"ipm3k5_sat": 1 / 6600}


def sampling_period(motor: str) -> float:
    """The sampling period (s) of preset `motor`'s drive: that of the registered observer
    whose paper drive it is (its class's `paper_T_s`), else `OTHER_T_S`, else 125 us."""
    for name in observer_names():
        preset, T_s = paper_drive(name)
        if preset == motor and observer_class(name).paper_motor is not None:
            return T_s
    return OTHER_T_S.get(motor, DEFAULT_PAPER_DRIVE[1])


#: The search strategies (`tuning.search`).
SEARCHES = ("hybrid", "gradient", "cmaes", "random", "local")
#: How the training and held-out runs combine their model errors
#: (`TuningProblem.train_errors`; `tuning.ERROR_PATTERNS`).
TRAIN_ERRORS = ("joint", "structured")

#: Default validation cases `(k_d, k_q, k_R, k_psi, k_noise)` (observer / plant; noise in
#: units of `noise_std`): matched; both inductances low, high, crossed; R_s high (hot
#: winding) and low; psi_f high and low (hot magnet); all at once with more noise; more
#: noise alone.
VALIDATION_CASES = (
    (1.0, 1.0, 1.0, 1.0, 1.0),
    (0.7, 0.7, 1.0, 1.0, 1.0),
    (1.3, 1.3, 1.0, 1.0, 1.0),
    (0.7, 1.3, 1.0, 1.0, 1.0),
    (1.3, 0.7, 1.0, 1.0, 1.0),
    (1.0, 1.0, 1.5, 1.0, 1.0),
    (1.0, 1.0, 0.7, 1.0, 1.0),
    (1.0, 1.0, 1.0, 1.1, 1.0),
    (1.0, 1.0, 1.0, 0.85, 1.0),
    (1.2, 1.2, 1.3, 0.9, 2.5),
    (1.0, 1.0, 1.0, 1.0, 3.0),
)

#: The observer model's L_d, L_q off by +-50 %, jointly and separately (the rest
#: matched): the cases `TuningProblem.wide_mismatch` adds to `VALIDATION_CASES`.
WIDE_CASES = tuple((k_d, k_q, 1.0, 1.0, 1.0) for k_d, k_q in (
    (0.5, 0.5), (1.5, 1.5), (0.5, 1.5), (1.5, 0.5),
    (0.5, 1.0), (1.5, 1.0), (1.0, 0.5), (1.0, 1.5)))
#: The observer-model / plant inductance ratios `TuningProblem.wide_mismatch` draws its
#: training and held-out runs from.
WIDE_MISMATCH_RANGE = (0.5, 1.5)
#: Training runs of `TuningProblem.wide_mismatch`: the default 24 over the +-30 % square
#: of (k_d, k_q), scaled to the +-50 % square's (1.0 / 0.6)^2 = 2.8 times the area and
#: rounded up to whole rounds of the three kinds (72): about as many draws per unit of
#: that area as the default.
WIDE_N_TRAIN = 72


def _mtime(path) -> int:
    if path is None:
        return 0
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return 0


@functools.lru_cache(maxsize=16)
def _drive(motor: str, motor_file: str | None, set_params: tuple, mtime: int) -> pj.Drive:
    del mtime  # part of the cache key: an edited motor file is read again
    drive = pj.preset(motor) if motor_file is None else pj.load_motor_file(motor_file)
    return pj.replace_params(drive, **dict(set_params)) if set_params else drive


def _bad(name, value, allowed):
    raise ValueError(f"`TuningProblem({name}=...)`: got {value!r}; {allowed}.")


@dataclasses.dataclass(frozen=True)
class TuningProblem:
    """Everything that defines a tuning run (validated on construction, immutable).

    **Drive and observer**

    - `observer`: a registered observer with a tunable design
      (`pmsmjax.observers.observer_names()`; its class's `tunable`).
    - `motor`: preset name; default (None) the observer's paper motor
      (`pmsmjax.observers.paper_drive`).
      `motor_file`: a motor file (TOML) instead. `set_params`: `((name, SI value), ...)`.
    - `T_s`: sampling period (s); default the motor's paper drive's (`sampling_period`, else
      125 us).
    - `noise_std`: current-sensor noise per component (A).
    - `speed_from_angle`: None (default) closes the speed loop on the observer's own
      speed estimate; a frequency (Hz) hands the controller the speed of the observer's
      angle through `pmsmjax.SpeedFromAngle` of that natural frequency, in every run
      (training, held-out and validation): the drive the design is for computes its
      speed that way.

    **Scenarios** (`tuning.scenarios`): closed-loop sensorless runs, speed controlled on
    the estimate, nothing imposed.

    - `t_end` (s): length of a training / held-out run (this and `val_t_end` are rounded
      to whole saved samples, `save_every` sampling periods); `n_train`, `n_heldout`: runs.
    - `speed_range` (p.u.): |speed| of the runs; `accel_range`: ramp acceleration as a
      fraction of what the drive's torque limit gives the unloaded rotor.
    - `load_max_pu`: largest load step (p.u. of rated torque).
    - `mismatch_range`, `resistance_range`, `flux_range`: observer-model / plant ratios of
      $L_d$ and $L_q$, $R_s$, $\\psi_f$ drawn for training and held-out runs.
    - `noise_range`: current noise in units of `noise_std`.
    - `train_errors`: how the training and held-out runs combine those errors:
      "structured" (default) in turn every parameter at once, both inductances, and each
      of $L_d$, $L_q$, $R_s$, $\\psi_f$ and the noise alone, the others matched
      (`tuning.ERROR_PATTERNS`), so that the search sees the kinds of error the
      validation cases hold (one at a time, the inductances jointly); "joint" every
      parameter in every run.
    - Validation (the runs the tuner never sees, `tuning.scenarios.validation_set`):
      `val_speeds_pu` (each with both signs), `val_cases` (rows `(k_d, k_q, k_R, k_psi,
      k_noise)`), `val_t_end` (s), `val_start_frac`, `val_load_pu`.
    - `low_speed_limit_pu` (p.u. of rated speed): the low-speed rule, fixed before
      tuning (`tuning.apply_low_speed_rule`). A run in which the sensored drive (the same
      controller on the true angle and speed, the same noise: `tuning.low_speed_runs`)
      turns slower than this is judged without its load step where that keeps the
      sensored drive above it (`verdict.low_speed_rule.unloaded`); otherwise it is beyond
      the observer's class: the verdict's counts leave it out and the report lists it
      apart, and such training and held-out runs are left out of the search's sets
      (`verdict.low_speed_rule.left_out`). None (default): the limit the
      observer's class declares (`low_speed_limit_pu`: 0.05 for li's PLL observers, 0,
      no run, for the others).

    **Design space** (`tuning.design_space`)

    - `ramp_lag_deg`: the angle lag the tracking loop may have at the drive's largest
      acceleration (sets the lowest tracking bandwidth, deg).
    - `w_T_s_max`: largest tracking bandwidth x `T_s` (discrete-time limit, -).
    - `damping_range`: damping ratios allowed (-).

    **Objective** (`tuning.objective`)

    - `theta_unit_deg`, `peak_unit_deg`, `noise_unit_rad_s`: units of the RMS angle
      error, the peak angle error and the speed-estimate noise in a run's loss;
      `w_peak`, `w_noise`: their weights (the RMS error has weight 1).
    - `lock_deg`: an angle error above this is out of lock (deg).
    - `cvar_fraction`: the tail averaged by the CVaR aggregate (worst fraction of runs).
    - `regression_tol`: no run's RMS angle error may exceed the reference design's by
      more than this (relative); `w_constraint`: the weight of that penalty.

    - `tune`: the design coordinates the searches change (names of
      `tuning.design_space.coordinate_names(observer)`, e.g. `("w2", "zeta2")` for the
      zhang2022 family, whose flux loop then keeps the paper's speed schedule (38));
      the others keep the paper's design. None (default): every coordinate. A class
      whose coordinates are one reparametrisation of its design
      (`tuning_coordinates`) changes all of them or none.

    **Search** (`tuning.search`)

    - `search`: "hybrid" (CMA-ES, then gradient polish; the default), "gradient",
      "cmaes", "random" or "local".
    - `budget`: closed-loop simulations each strategy may run (a gradient of the
      training batch counts as `n_train` simulations).
    - `learning_rate`, `clip_norm`: Adam step (unconstrained units) and gradient clip.
    - `population`: CMA-ES population per generation.
    - `seed`: noise keys, scenario draws and the searches' randomness.
    - `save_every`: samples kept per run (every n-th).
    """

    observer: str = "eso"
    motor: str | None = None
    motor_file: str | None = None
    set_params: tuple = ()
    T_s: float | None = None
    noise_std: float = 0.02
    speed_from_angle: float | None = None
    # scenarios
    t_end: float = 0.3
    n_train: int = 24
    n_heldout: int = 24
    speed_range: tuple = (0.05, 1.0)
    accel_range: tuple = (0.2, 0.8)
    load_max_pu: float = 1.0
    mismatch_range: tuple = (0.7, 1.3)
    resistance_range: tuple = (0.7, 1.5)
    flux_range: tuple = (0.85, 1.1)
    noise_range: tuple = (1.0, 3.0)
    train_errors: str = "structured"
    val_speeds_pu: tuple = (0.1, 0.4, 0.5, 0.8)
    val_cases: tuple = VALIDATION_CASES
    val_t_end: float = 0.5
    val_start_frac: float = 0.6
    val_load_pu: float = 0.4
    low_speed_limit_pu: float | None = None
    # design space
    ramp_lag_deg: float = 10.0
    w_T_s_max: float = 0.15
    damping_range: tuple = (0.4, 2.5)
    # objective
    theta_unit_deg: float = 1.0
    peak_unit_deg: float = 10.0
    noise_unit_rad_s: float = 10.0
    w_peak: float = 0.5
    w_noise: float = 0.5
    lock_deg: float = 45.0
    cvar_fraction: float = 0.25
    regression_tol: float = 0.10
    w_constraint: float = 20.0
    # what the searches change
    tune: tuple | None = None
    # search
    search: str = "hybrid"
    budget: int = 1200
    learning_rate: float = 0.08
    clip_norm: float = 1.0
    population: int = 8
    seed: int = 0
    save_every: int = 4

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        if self.observer not in observer_names():
            _bad("observer", self.observer, f"choose one of {', '.join(observer_names())}")
        if not observer_class(self.observer).tunable:
            _bad("observer", self.observer, "it declares no tunable design (its class's "
                                            "`tunable` is empty)")
        if self.motor_file is not None:
            set_("motor_file", os.path.abspath(self.motor_file))
            if not os.path.isfile(self.motor_file):
                _bad("motor_file", self.motor_file, "no such file")
        elif self.motor is None:
            set_("motor", paper_drive(self.observer)[0])
        if self.motor_file is None and self.motor not in pj.PRESET_NAMES:
            _bad("motor", self.motor, f"choose one of {', '.join(pj.PRESET_NAMES)} or give "
                                      f"`motor_file`")
        if self.T_s is None:
            set_("T_s", sampling_period(self.motor) if self.motor_file is None
                 else DEFAULT_PAPER_DRIVE[1])
        for k in ("set_params", "speed_range", "accel_range", "mismatch_range",
                  "resistance_range", "flux_range", "noise_range", "val_speeds_pu",
                  "damping_range"):
            set_(k, tuple(tuple(x) if isinstance(x, list) else x for x in getattr(self, k)))
        set_("val_cases", tuple(tuple(float(v) for v in row) for row in self.val_cases))
        self.drive()  # a bad motor file or replacement is an error now, named
        for keys, ok, allowed in (
                (("T_s", "t_end", "val_t_end", "noise_unit_rad_s", "theta_unit_deg",
                  "peak_unit_deg", "ramp_lag_deg", "w_T_s_max", "lock_deg"),
                 lambda v: v > 0, "a finite number > 0 is allowed"),
                (("noise_std", "load_max_pu", "w_peak", "w_noise", "regression_tol",
                  "w_constraint", "val_load_pu"),
                 lambda v: v >= 0, "a finite number >= 0 is allowed")):
            for k in keys:
                v = getattr(self, k)
                if not (isinstance(v, (int, float)) and math.isfinite(v) and ok(v)):
                    _bad(k, v, allowed)
        f = self.speed_from_angle
        if f is not None and not (isinstance(f, (int, float)) and math.isfinite(f) and f > 0):
            _bad("speed_from_angle", f, "None or a frequency > 0 (Hz)")
        for k in ("speed_range", "accel_range", "mismatch_range", "resistance_range",
                  "flux_range", "noise_range", "damping_range"):
            lo_hi = getattr(self, k)
            if len(lo_hi) != 2 or not (0 < lo_hi[0] <= lo_hi[1]):
                _bad(k, lo_hi, "(lo, hi) with 0 < lo <= hi is allowed")
        for k in ("n_train", "n_heldout", "budget", "population", "save_every"):
            v = getattr(self, k)
            if not (isinstance(v, int) and v >= 1):
                _bad(k, v, "an integer >= 1 is allowed")
        if self.population < 4:
            _bad("population", self.population, "CMA-ES needs at least 4")
        if self.budget < 2 * self.n_train:
            _bad("budget", self.budget, f"at least two evaluations of the training batch "
                                        f"(2 x n_train = {2 * self.n_train}) are needed")
        if not (0 < self.cvar_fraction <= 1):
            _bad("cvar_fraction", self.cvar_fraction, "0 < fraction <= 1 is allowed")
        if self.train_errors not in TRAIN_ERRORS:
            _bad("train_errors", self.train_errors, f"choose one of {', '.join(TRAIN_ERRORS)}")
        if self.search not in SEARCHES:
            _bad("search", self.search, f"choose one of {', '.join(SEARCHES)}")
        if not self.val_speeds_pu or any(not (0 < abs(s) <= 2) for s in self.val_speeds_pu):
            _bad("val_speeds_pu", self.val_speeds_pu, "nonzero speeds within 2 p.u.")
        if any(len(r) != 5 or min(r) <= 0 for r in self.val_cases):
            _bad("val_cases", self.val_cases, "rows (k_d, k_q, k_R, k_psi, k_noise) > 0")
        if self.tune is not None:
            from .design_space import coordinate_names

            set_("tune", tuple(self.tune) if isinstance(self.tune, (list, tuple))
                 else (self.tune,))
            names = coordinate_names(self.observer)
            bad = [n for n in self.tune if n not in names]
            if bad or not self.tune or len(set(self.tune)) != len(self.tune):
                _bad("tune", self.tune, f"distinct names among the {self.observer} "
                                        f"observer's coordinates: {', '.join(names)}")
            joint = tuple(observer_class(self.observer).tuning_coordinates)
            if joint and not set(joint) <= set(self.tune):
                _bad("tune", self.tune, f"all of {', '.join(joint)} (one "
                                        f"reparametrisation of the {self.observer} "
                                        f"observer's design) or None")
        if self.low_speed_limit_pu is None:
            set_("low_speed_limit_pu",
                 float(observer_class(self.observer).low_speed_limit_pu))
        v = self.low_speed_limit_pu
        if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v < 1):
            _bad("low_speed_limit_pu", v, "None or a speed 0 <= v < 1 (p.u. of rated)")
        if not (0 < self.val_start_frac < 1):
            _bad("val_start_frac", self.val_start_frac, "0 < fraction < 1")
        for k in ("t_end", "val_t_end"):
            # whole saved samples (a run keeps every save_every-th of round(t / T_s)
            # steps): rounded to the nearest, at most save_every T_s / 2 away
            block = self.T_s * self.save_every
            if abs(getattr(self, k) / block - round(getattr(self, k) / block)) > 1e-9:
                set_(k, max(1, round(getattr(self, k) / block)) * block)
            if getattr(self, k) < 40 * self.T_s * self.save_every:
                _bad(k, getattr(self, k), f"runs of at least 40 saved samples "
                                          f"(>= {40 * self.T_s * self.save_every:g} s)")

    # --- what the stages take -----------------------------------------------------
    def drive(self) -> pj.Drive:
        """The plant (`pmsmjax.Drive`)."""
        return _drive(self.motor, self.motor_file, self.set_params,
                      _mtime(self.motor_file) if self.motor_file else 0)

    def controller(self) -> pj.FOC:
        """The drive's field-oriented controller (the library's default for the drive)."""
        return pj.FOC.from_drive(self.drive())

    def paper_observer(self, motor=None):
        """The observer with its paper's design for the drive (`motor`: the observer's
        machine model, default the drive's)."""
        from pmsmjax.observers import make_observer

        return make_observer(self.observer, self.drive(), motor=motor)

    def replace(self, **changes) -> TuningProblem:
        """A copy with fields replaced (checked again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The fields as plain data (for `summary.json`), and the plant's magnetic model:
        `"saturation"` is None for constant inductances, else the model's class and the
        constants the observer deploys (its L_d, L_q, psi_f)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        m = self.drive().three_phase_motor
        out["saturation"] = None if m.magnetic is None else {
            "model": type(m.magnetic).__name__,
            "deployed": {"L_d": float(m.L_d), "L_q": float(m.L_q), "psi_f": float(m.psi_f)}}
        return out

    @classmethod
    def quick(cls, **changes) -> TuningProblem:
        """A small problem for tests and smoke runs: few short runs, small budget."""
        kw = dict(t_end=0.15, n_train=6, n_heldout=6, val_speeds_pu=(0.4, 0.8),
                  val_cases=VALIDATION_CASES[:3], val_t_end=0.25, budget=72,
                  population=6, save_every=4)
        kw.update(changes)
        return cls(**kw)

    @classmethod
    def wide_mismatch(cls, **changes) -> TuningProblem:
        """The sets with the observer model's L_d and L_q off by up to +-50 %: training
        and held-out runs drawn from `WIDE_MISMATCH_RANGE`, and the validation cases
        `VALIDATION_CASES` + `WIDE_CASES` (both inductances +-50 %, jointly, crossed and
        one at a time); `WIDE_N_TRAIN` training runs for the larger square; everything
        else as the defaults (`changes` override, e.g. `regression_tol=0.05`). The
        measured outcome is in docs/tuning.md, "Inductance mismatch up to +-50 %"."""
        kw = dict(mismatch_range=WIDE_MISMATCH_RANGE, val_cases=VALIDATION_CASES + WIDE_CASES,
                  n_train=WIDE_N_TRAIN)
        kw.update(changes)
        return cls(**kw)


__all__ = ["OTHER_T_S", "SEARCHES", "TRAIN_ERRORS", "TuningProblem", "VALIDATION_CASES",
           "WIDE_CASES", "WIDE_MISMATCH_RANGE", "WIDE_N_TRAIN", "sampling_period"]
