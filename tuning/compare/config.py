r"""The configuration of the observer comparison (`python -m tuning compare`): the common
grid, the designs and which observers apply.

**The common grid.** Every observer runs the same closed-loop, speed-controlled,
sensorless runs, built like the tuner's validation runs (`tuning.scenarios`): the speed
loop is fed by the observer's $\hat\omega$ and the current control runs in its frame
$\hat\theta$; the run starts at `start_frac` x the final speed (observer on the true
state), the speed reference ramps to the final speed over $[0.1, 0.3]\,t_{end}$, and a
braking load steps from 0 to the run's load at $0.6\,t_{end}$. The grid is the product of

- `speeds_pu`, each with both signs (p.u. of rated speed);
- `loads_pu` (p.u. of rated torque; 0 = no load step);
- `cases`: observer-model mismatch rows $(k_d, k_q, k_R, k_\psi)$, observer value / plant
  value of $L_d$, $L_q$, $R_s$, $\psi_f$;

with current-sensor noise `noise_std` (A per component) drawn from one key per grid point,
the same for every observer (a fair comparison: every observer sees the same noise).

**Designs.** "paper": the observer's paper design (`make_observer`, `from_drive`);
"tuned": the closed-loop tuner's search (`tuning.search`, strategy `tuner`, default its
hybrid of CMA-ES and the gradient) from it, on the tuner's small problem
(`tuning_problem`: `TuningProblem.quick` for the drive, `tune_steps` evaluations of its
training batch), in the tuner's design space (`tuning.DesignSpace`), cached in the job
folder (`tuned/NAME.json`, the physical coordinates) so that a resumed job does not tune
again. Or, for the observers `tuned_designs` names, the design a full tuning run
(`python -m tuning`) deployed, given by its coordinates (`tuned_designs_from` reads them
from such runs' output folders: `--tuned-from DIR ...` on the command line); nothing is
tuned for those.

**Which observers apply.** Every registered observer estimates from the alpha-beta
subspace (for a dual three-phase machine, the alpha-beta subspace of the VSD), so every
observer whose `from_drive` accepts the drive applies; an observer whose `from_drive`
raises `ValueError` for the motor is listed under `skipped` with the message.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os

import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import grid_product
from pmsmjax.observers import (
    make_observer as registry_observer,
    observer_class,
    observer_names,
)

from ..design_space import coordinate_names
from ..problem import TuningProblem, _drive, _mtime


DESIGNS = ("paper", "tuned")
TUNERS = ("hybrid", "gradient", "cmaes", "random", "local", "none")
#: Observer-model mismatch cases `(k_d, k_q, k_R, k_psi)` (observer value / plant value):
#: matched; both inductances low and high; crossed; R_s high (hot winding) and low;
#: psi_f high and low (hot magnet); everything at once.
CASES = (
    (1.0, 1.0, 1.0, 1.0),
    (0.7, 0.7, 1.0, 1.0),
    (1.3, 1.3, 1.0, 1.0),
    (0.7, 1.3, 1.0, 1.0),
    (1.3, 0.7, 1.0, 1.0),
    (1.0, 1.0, 1.5, 1.0),
    (1.0, 1.0, 0.7, 1.0),
    (1.0, 1.0, 1.0, 1.1),
    (1.0, 1.0, 1.0, 0.85),
    (1.2, 1.2, 1.3, 0.9),
)
CASE_NAMES = ("k_d", "k_q", "k_R", "k_psi")
#: Samples kept of each run's angle and speed-estimate errors (for the time traces).
TRACE_SAMPLES = 200


def case_label(c: dict) -> str:
    """A mismatch case (`{"k_d": ..., ...}`) in words: `"d 0.7, q 1.3"`, or `"matched"`."""
    parts = [f"{k[2:]} {v:g}" for k, v in c.items() if k in CASE_NAMES and v != 1.0]
    return ", ".join(parts) if parts else "matched"


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    """Everything that defines a comparison (see the module docstring).

    - `motor`: preset name; `observers`: registered names (None: every one that applies).
    - `motor_file`: a motor file (TOML) of your own drive instead of a preset (stored as
      an absolute path; `motor` becomes the name the file gives its drive);
      `set_params`: `((name, value), ...)` drive parameters replaced (SI units), as
      `TuningProblem`'s.
    - `T_s` (s), `t_end` (s): sampling period and length of each run; `save_every`: samples
      kept (every n-th).
    - `speeds_pu` (p.u., > 0, each run with both signs), `loads_pu` (p.u. of rated torque,
      >= 0), `cases`: mismatch rows `(k_d, k_q, k_R, k_psi)`.
    - `start_frac`: the run starts at this fraction of its final speed.
    - `noise_std`: current noise (A per component); `seed`: of the noise keys.
    - `lock_deg` (deg), `settle_band_deg` (deg): loss-of-lock threshold and settling band.
    - `tuner`: the closed-loop tuner's search strategy (`tuning.search`: "hybrid",
      "gradient", "cmaes", "random", "local") or "none" (no tuned design);
      `tune_steps`: its budget in evaluations of the training batch (simulations:
      `tune_steps` x the batch size).
    - `harmonic_orders`, `harmonic_speeds_pu`: of the harmonic sensitivity.
    - `chunk_size`: runs per sweep chunk (the unit of resume); None (default): chosen by
      `run_sweep` from the measured cost (chunks of a few seconds; a sweep of the
      comparison's size is one chunk, evaluated at one vmap width).
    - `analysis`: run the generic equilibrium analysis on the grid (its compilation is the
      largest part of a small comparison; False: `feasible_fraction` is flagged).
    - `speed_from_angle`: None (default), or the natural frequency (Hz) of a tracking
      loop whose speed of the observer's angle closes every run's speed loop
      (`pmsmjax.SpeedFromAngle`) in place of the observer's own speed estimate; the tuned
      design is tuned with it too (`TuningProblem.speed_from_angle`).
    - `tuned_designs`: `((observer, ((coordinate, value), ...)), ...)`: the "tuned"
      design of those observers, in the physical coordinates of the tuner's design space
      (`tuning.DesignSpace`, units as its `bounds_table` gives them; a coordinate not
      given keeps the paper design's value), e.g. the design a `python -m tuning` run
      deployed (`tuned_designs_from`); the other observers are tuned as above.
    """

    motor: str = "zhang750"
    observers: tuple | None = None
    motor_file: str | None = None
    set_params: tuple = ()
    T_s: float = 125e-6
    t_end: float = 0.4
    save_every: int = 2
    speeds_pu: tuple = (0.05, 0.1, 0.25, 0.5, 1.0)
    loads_pu: tuple = (0.0, 0.5, 1.0)
    cases: tuple = CASES
    start_frac: float = 0.6
    noise_std: float = 0.02
    seed: int = 0
    lock_deg: float = pj.LOCK_DEG
    settle_band_deg: float = 2.0
    tuner: str = "hybrid"
    tune_steps: int = 12
    harmonic_orders: tuple = (-5, 7)
    harmonic_speeds_pu: tuple = (0.1, 0.5, 1.0)
    chunk_size: int | None = None
    analysis: bool = True
    speed_from_angle: float | None = None
    tuned_designs: tuple = ()

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        if self.motor_file is None and self.motor not in pj.PRESET_NAMES:
            raise ValueError(f"`CompareConfig(motor=...)` must be one of "
                             f"{', '.join(pj.PRESET_NAMES)} (or give `motor_file`); got "
                             f"{self.motor!r}.")
        try:
            set_("set_params", tuple((str(n), float(v)) for n, v in self.set_params))
        except (TypeError, ValueError):
            raise ValueError(f"`CompareConfig(set_params=...)` must be (name, value) pairs "
                             f"(SI units); got {self.set_params!r}.") from None
        if self.motor_file is not None:
            set_("motor_file", os.path.abspath(os.fspath(self.motor_file)))
            try:
                set_("motor", self.drive().name)
            except OSError as e:
                raise ValueError(f"`CompareConfig(motor_file=...)` cannot be read: {e}"
                                 ) from None
        if self.observers is not None:
            obs = tuple(str(o).strip().lower() for o in self.observers if str(o).strip())
            unknown = [o for o in obs if o not in observer_names()]
            if not obs or unknown:
                raise ValueError(f"`CompareConfig(observers=...)` must be registered "
                                 f"observers ({', '.join(observer_names())}); got "
                                 f"{self.observers!r}.")
            set_("observers", obs)
        for name in ("speeds_pu", "loads_pu", "harmonic_orders", "harmonic_speeds_pu"):
            v = tuple(float(x) for x in np.asarray(getattr(self, name), float).reshape(-1))
            if not v or not all(math.isfinite(x) for x in v):
                raise ValueError(f"`CompareConfig({name}=...)` must be finite numbers (at "
                                 f"least one); got {getattr(self, name)!r}.")
            set_(name, v)
        if any(not 0 < s <= 2 for s in self.speeds_pu):
            raise ValueError(f"`CompareConfig(speeds_pu=...)` must lie in (0, 2] p.u. (both "
                             f"signs are run); got {self.speeds_pu}.")
        if any(x < 0 for x in self.loads_pu):
            raise ValueError(f"`CompareConfig(loads_pu=...)` must be >= 0; got "
                             f"{self.loads_pu}.")
        set_("harmonic_orders", tuple(int(x) for x in self.harmonic_orders))
        cases = np.asarray(self.cases, dtype=float)
        if cases.ndim != 2 or cases.shape[1] != 4 or cases.shape[0] == 0 \
                or np.any(~np.isfinite(cases)) or np.any(cases <= 0):
            raise ValueError("`CompareConfig(cases=...)` must be rows (k_d, k_q, k_R, k_psi) "
                             f"of factors > 0; got {self.cases!r}.")
        set_("cases", tuple(tuple(float(x) for x in r) for r in cases))
        if self.tuner not in TUNERS:
            raise ValueError(f"`CompareConfig(tuner=...)` must be one of {', '.join(TUNERS)}; "
                             f"got {self.tuner!r}.")
        for name in ("tune_steps", "chunk_size", "save_every", "seed"):
            v = getattr(self, name)
            if name == "chunk_size" and v is None:
                continue
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"`CompareConfig({name}=...)` must be an integer >= 0; got "
                                 f"{v!r}.")
        if (self.chunk_size is not None and self.chunk_size < 1) or self.save_every < 1:
            raise ValueError("`CompareConfig(chunk_size=..., save_every=...)` must be >= 1.")
        for name in ("lock_deg", "settle_band_deg", "T_s", "t_end"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"`CompareConfig({name}=...)` must be a finite number > 0; "
                                 f"got {v!r}.")
        f = self.speed_from_angle
        if f is not None:
            if isinstance(f, bool) or not isinstance(f, int | float) or not (
                    math.isfinite(f) and f > 0):
                raise ValueError(f"`CompareConfig(speed_from_angle=...)` must be None or a "
                                 f"frequency > 0 (Hz); got {f!r}.")
            set_("speed_from_angle", float(f))
        set_("tuned_designs", _check_designs(self.tuned_designs, self.observers))
        # the tuner's problem checks the rest (run length against the sampling period)
        self.tuning_problem(observer_names()[0])

    @classmethod
    def quick(cls, **changes) -> CompareConfig:
        """The `--quick` comparison, a first look in about 80 s on two cores: the
        paper designs only (`tuner="none"`) and no generic equilibrium analysis
        (`analysis=False`), whose compilations per observer are what a small comparison
        spends its time on (see BENCHMARKS.md); 4 kHz, 0.3 s runs, speeds +-{0.05, 0.25,
        1} p.u., no load and rated load, five mismatch cases. The tuned designs and the
        feasible fraction are flagged as not computed; the default job has them."""
        kw = dict(T_s=250e-6, t_end=0.3, speeds_pu=(0.05, 0.25, 1.0), loads_pu=(0.0, 1.0),
                  cases=(CASES[0], CASES[3], CASES[5], CASES[8], CASES[9]), tune_steps=4,
                  harmonic_speeds_pu=(0.25, 1.0), tuner="none", analysis=False)
        kw.update(changes)
        return cls(**kw)

    def to_dict(self) -> dict:
        """The fields as JSON values; `motor_file`, `set_params`, `speed_from_angle` and
        `tuned_designs` only when given, so that a preset job keeps the fingerprint (and
        resumes) it had before they existed."""
        d = dataclasses.asdict(self)
        for k, empty in (("motor_file", None), ("set_params", ()), ("speed_from_angle", None),
                         ("tuned_designs", ())):
            if d[k] == empty:
                del d[k]
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> CompareConfig:
        """The configuration of `to_dict` (e.g. the `config` of a job's `job.json`)."""
        def tup(v):
            return tuple(tup(x) for x in v) if isinstance(v, list) else v

        return cls(**{k: tup(v) for k, v in d.items()})

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()
                              ).hexdigest()[:16]

    def drive(self) -> pj.Drive:
        """The preset `motor` or the drive of `motor_file`, with `set_params` applied."""
        return _drive(self.motor, self.motor_file, self.set_params,
                      _mtime(self.motor_file))

    def _drive_kw(self) -> dict:
        """The drive of a `TuningProblem`: the preset, or the motor file, and `--set`."""
        if self.motor_file is None:
            return dict(motor=self.motor, set_params=self.set_params)
        return dict(motor_file=self.motor_file, set_params=self.set_params)

    def tuning_problem(self, observer: str) -> TuningProblem:
        """The tuner's small problem for `observer` on this comparison's drive, sampling
        period, noise and seed (`TuningProblem.quick`), with a budget of `tune_steps`
        evaluations of its training batch."""
        q = TuningProblem.quick(**self._drive_kw(), observer=observer, T_s=self.T_s,
                                noise_std=self.noise_std, seed=self.seed)
        return q.replace(budget=max(self.tune_steps, 2) * q.n_train,
                         speed_from_angle=self.speed_from_angle)

    def grid(self, index: bool = False):
        """The common grid as a `SweepGrid` (axes: signed speed, load, case index);
        `index`: with the column `index` (the point number: of the noise keys)."""
        speeds = np.array([s for v in self.speeds_pu for s in (-v, v)])
        g = grid_product(speed_pu=np.sort(speeds), load_pu=np.asarray(self.loads_pu),
                         case=np.arange(len(self.cases)))
        if index:
            g["index"] = np.arange(len(g["case"]))
        return g


def _check_designs(designs, observers) -> tuple:
    """`CompareConfig.tuned_designs` as nested tuples of (str, float), checked: registered
    observers, each once and among `observers` (where given), coordinates of its design
    space, finite values > 0."""
    where = "`CompareConfig(tuned_designs=...)`"
    out, seen = [], set()
    try:
        items = [(str(n), tuple((str(k), float(v)) for k, v in c)) for n, c in designs]
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be (observer, ((coordinate, value), ...)) pairs; "
                         f"got {designs!r}.") from None
    for name, coords in items:
        if name not in observer_names():
            raise ValueError(f"{where}: {name!r} is no registered observer (registered: "
                             f"{', '.join(observer_names())}).")
        if name in seen:
            raise ValueError(f"{where}: {name!r} is given twice.")
        if observers is not None and name not in observers:
            raise ValueError(f"{where}: {name!r} is not among the compared observers "
                             f"({', '.join(observers)}).")
        seen.add(name)
        allowed = coordinate_names(name)
        for k, v in coords:
            if k not in allowed:
                raise ValueError(f"{where}: {k!r} is no design coordinate of {name!r} "
                                 f"(its coordinates: {', '.join(allowed)}).")
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{where}: {name} {k} = {v!r}; a coordinate is a finite "
                                 f"value > 0.")
        out.append((name, coords))
    return tuple(out)


def tuned_designs_from(folders, motor: str) -> tuple:
    """`CompareConfig.tuned_designs` from the output folders of `python -m tuning` runs
    (each folder's `design.json`: the deployed design's observer and coordinates), each
    checked to have been tuned on the drive named `motor` (its `summary.json`).
    `ValueError` naming the folder where a file is missing or unreadable, or the drive
    differs."""
    from ..report.summary import DESIGN_FILE, SUMMARY_FILE

    out = []
    for folder in folders:
        try:
            with open(os.path.join(folder, DESIGN_FILE)) as f:
                d = json.load(f)
            with open(os.path.join(folder, SUMMARY_FILE)) as f:
                tuned_on = json.load(f)["motor"]
            name, coords = d["observer"], d["coordinates"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"`--tuned-from {folder}`: not the output folder of a "
                             f"`python -m tuning` run ({DESIGN_FILE} and {SUMMARY_FILE} "
                             f"with the deployed design): {e}") from None
        if tuned_on != motor:
            raise ValueError(f"`--tuned-from {folder}`: its {name} design was tuned on "
                             f"{tuned_on!r}; this comparison runs {motor!r}.")
        out.append((name, tuple(sorted(coords.items()))))
    return tuple(out)


def applicable_observers(config: CompareConfig) -> tuple[dict, dict]:
    """`({name: class name}, {name: reason})`: the observers of the comparison that apply
    to the motor (their `from_drive` accepts it) and those that do not."""
    names = config.observers or observer_names()
    drive = config.drive()
    ok, skipped = {}, {}
    for n in names:
        try:
            registry_observer(n, drive)
            config.tuning_problem(n)
        except ValueError as e:
            skipped[n] = str(e)
        else:
            ok[n] = observer_class(n).__name__
    return ok, skipped


__all__ = ["CASES", "CASE_NAMES", "DESIGNS", "TRACE_SAMPLES", "TUNERS", "CompareConfig",
           "applicable_observers", "case_label", "tuned_designs_from"]
