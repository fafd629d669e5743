r"""Which observer for my drive? Every registered observer, paper design and tuned, on one
common grid (`python -m tuning compare`).

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

**Per-run metrics** (`run_metrics`; $\tilde\theta = \theta - \hat\theta$ wrapped, deg,
and $\tilde\omega = \omega - \hat\omega$, rad/s, on the saved samples):

- `static_deg`: the static angle error, the mean of $\tilde\theta$ over the *static
  window*, the last `STATIC_WINDOW` = 20 % of the run (after the ramp and the load step);
- `rms_deg`: RMS of $\tilde\theta$ over the whole run (what the ramp, the load step, the
  mismatch and the noise cause together);
- `max_abs_deg`: largest $|\tilde\theta|$ over the run;
- `settle_s`: settling time, from the start of the ramp ($0.1\,t_{end}$) until
  $|\tilde\theta - \tilde\theta_{static}| \le$ `settle_band_deg` for good; NaN if the
  last sample is outside the band (never settled);
- `noise_rad_s`: speed-estimate noise, the standard deviation of $\tilde\omega$ over the
  static window;
- `lost_lock`: the run lost lock, by the library's one definition (`pmsmjax.lock_status`:
  the mean $|\tilde\theta|$ over 10 ms above `lock_deg`, default 45 deg, after lock was acquired,
  or the run diverged or produced a non-finite sample).

**Per-observer metrics** (`aggregate`), over the runs that kept lock (runs that lost lock
are counted and located instead, their angle error is meaningless):

- `static_worst_deg`: largest $|$`static_deg`$|$; `static_rms_deg`: RMS of `static_deg`;
- `rms_worst_deg`: largest `rms_deg`;
- `settle_worst_s`, `settle_median_s`: over the runs that settled; `n_unsettled` counts
  the others;
- `noise_median_rad_s`, `noise_worst_rad_s`;
- `lost_lock`: count, and `lost_lock_where`: the grid points (speed, load, case);
- `feasible_fraction`: the fraction of the analysis grid (the same speeds, both signs,
  loads and mismatch cases, at constant speed and current) where the generic analysis
  (`pmsmjax.analysis.equilibria_traced`, or the family's own route) finds the designed
  equilibrium stable and no other stable equilibrium;
- `harmonic_deg_per_pct`: the largest peak angle-error ripple per 1 % back-EMF harmonic
  (`pmsmjax.analysis.harmonic_ripple`, orders `harmonic_orders` at `harmonic_speeds_pu`,
  matched model, no load), where that analysis is available;
- `observer_us_per_step`: compute cost of one observer step (us; `pmsmjax.replay` of a
  recorded run, batch 1, best of three after compilation; in the `timing` block of the
  JSON: it is a measurement of this machine, not of the observer alone).

A metric that cannot be computed is `null` in the JSON with its reason in `flags`.

**Designs.** "paper": the observer's paper design (`make_observer`, `from_drive`);
"tuned": the closed-loop tuner's search (`tuning.search`, strategy `tuner`, default its
hybrid of CMA-ES and the gradient) from it, on the tuner's small problem
(`tuning_problem`: `TuningProblem.quick` for the drive, `tune_steps` evaluations of its
training batch), in the tuner's design space (`tuning.DesignSpace`), cached in the job
folder (`tuned/NAME.json`, the physical coordinates) so that a resumed job does not tune
again.

**Which observers apply.** Every registered observer estimates from the alpha-beta
subspace (for a dual three-phase machine, the alpha-beta subspace of the VSD), so every
observer whose `from_drive` accepts the drive applies; an observer whose `from_drive`
raises `ValueError` for the motor is listed under `skipped` with the message.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import pathlib
import time

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import (
    SweepGrid,
    equilibria_traced,
    grid_product,
    harmonic_ripple,
    run_sweep,
)
from pmsmjax.observers import (
    OperatingPoint,
    make_observer as registry_observer,
    observer_class,
    observer_names,
)

from ..design_space import DesignSpace
from ..evaluate import Evaluator
from ..objective import objective
from ..problem import TuningProblem, _drive, _mtime
from ..report.summary import _clean
from ..scenarios import (
    VAL_LOAD_STEP,
    VAL_RAMP,
    ScenarioSet,
    observer_model,
    simulate_set,
    training_set,
)
from ..search import STRATEGIES


FORMAT = "pmsmjax-compare/1"
#: The static window: the last fraction of each run (after the ramp and the load step).
STATIC_WINDOW = 0.2
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
#: Environment variable (tests): stop the job with `CompareInterrupted` after this many
#: units of work (a tuning, a sweep chunk, a cost measurement).
STOP_ENV = "PMSMJAX_COMPARE_STOP_AFTER"
#: Samples kept of each run's angle and speed-estimate errors (for the time traces).
TRACE_SAMPLES = 200
#: Keys of comparison.json that hold measurements of the machine (they differ between any
#: two runs, a resumed one included); the last column of comparison.md is one of them.
TIMING_KEYS = ("observer_us_per_step",)


class CompareInterrupted(RuntimeError):
    """Raised when the job stops after `STOP_ENV` units (a simulated interruption)."""


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
        """The fields as JSON values; `motor_file` and `set_params` only when given, so
        that a preset job keeps the fingerprint (and resumes) it had before they
        existed."""
        d = dataclasses.asdict(self)
        for k, empty in (("motor_file", None), ("set_params", ())):
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
        return q.replace(budget=max(self.tune_steps, 2) * q.n_train)

    def grid(self, index: bool = False):
        """The common grid as a `SweepGrid` (axes: signed speed, load, case index);
        `index`: with the column `index` (the point number: of the noise keys)."""
        speeds = np.array([s for v in self.speeds_pu for s in (-v, v)])
        g = grid_product(speed_pu=np.sort(speeds), load_pu=np.asarray(self.loads_pu),
                         case=np.arange(len(self.cases)))
        if index:
            g["index"] = np.arange(len(g["case"]))
        return g


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


# ---------------------------------------------------------------------------------------
# Per-run metrics and the per-point functions of the sweeps
# ---------------------------------------------------------------------------------------

def run_metrics(traj: pj.Trajectory, config: CompareConfig) -> dict:
    """Per-run metrics of a (batched) trajectory of the common grid (module docstring)."""
    t = traj.t
    th = jnp.degrees(traj.theta_err)
    w_err = traj.w_m - traj.w_hat
    fin = jnp.isfinite(th) & jnp.isfinite(w_err)
    th = jnp.where(fin, th, 0.0)
    w_err = jnp.where(fin, w_err, 0.0)
    half = 0.5 * config.T_s
    win = t >= (1 - STATIC_WINDOW) * config.t_end - half
    nw = jnp.sum(win, -1)
    static = jnp.sum(jnp.where(win, th, 0.0), -1) / nw
    w_mean = jnp.sum(jnp.where(win, w_err, 0.0), -1) / nw
    noise = jnp.sqrt(jnp.sum(jnp.where(win, (w_err - w_mean[..., None]) ** 2, 0.0), -1) / nw)
    rms = jnp.sqrt(jnp.mean(th ** 2, -1))
    max_abs = jnp.max(jnp.abs(th), -1)
    t0 = VAL_RAMP[0] * config.t_end
    after = t >= t0 - half
    out = after & (jnp.abs(th - static[..., None]) > config.settle_band_deg)
    idx = jnp.arange(t.shape[-1])
    last_out = jnp.max(jnp.where(out, idx, -1), -1)
    n = t.shape[-1]
    t_set = jnp.take_along_axis(t, jnp.clip(last_out + 1, 0, n - 1)[..., None], -1)[..., 0]
    settle = jnp.where(last_out < 0, 0.0, t_set - t0)
    settle = jnp.where(last_out >= n - 1, jnp.nan, settle)
    lost = pj.lock_status(t, traj.theta_err, ok=traj.ok & jnp.all(fin, -1),
                          lock_deg=config.lock_deg)["lost"]
    return dict(static_deg=static, rms_deg=rms, max_abs_deg=max_abs, settle_s=settle,
                noise_rad_s=noise, lost_lock=lost)


def _design_columns(x) -> dict:
    """The design's physical coordinates as grid columns `design_000`, ... (one value per
    column, the same at every point; none for the paper's design, `x` None)."""
    if x is None:
        return {}
    return {f"design_{i:03d}": float(v) for i, v in enumerate(np.asarray(x))}


@functools.lru_cache(maxsize=32)
def _space(config: CompareConfig, name: str) -> DesignSpace:
    return DesignSpace(config.tuning_problem(name))


@functools.lru_cache(maxsize=64)
def _sweep_fns(config: CompareConfig, name: str, n_coords: int):
    """The per-point functions of the two sweeps of observer `name` for a design of
    `n_coords` coordinates (0: the paper's design): one function object per observer,
    kind of design and kind of sweep, so that a resumed job in the same process compiles
    nothing."""
    def design(p):
        return None if n_coords == 0 else jnp.stack(
            [p[f"design_{i:03d}"] for i in range(n_coords)])

    def f_runs(p):
        return run_point(design(p), config, name, p)

    def f_feas(p):
        return feasibility_point(design(p), config, name, p)

    return f_runs, f_feas


def run_point(design, config: CompareConfig, kind: str, point: dict) -> dict:
    """Simulate one point of the common grid (`tuning.scenarios.simulate_set`, the runs
    of the tuner's validation set) with the design `design` (physical coordinates of the
    tuner's design space; None: the paper's) and return its `run_metrics`. `point`:
    `speed_pu` (signed), `load_pu`, `case` (index into `config.cases`), `index` (of the
    noise key)."""
    drive = config.drive()
    space = _space(config, kind)
    cases = jnp.asarray(config.cases)
    k = cases[point["case"].astype(int)]
    sp = jnp.asarray(point["speed_pu"])[None]
    key = jr.fold_in(jr.PRNGKey(config.seed), point["index"].astype(jnp.uint32))
    q = lambda f: jnp.full(1, round(f * config.t_end / config.T_s) * config.T_s)  # noqa
    sset = ScenarioSet(s0=config.start_frac * sp, s1=sp, t0=q(VAL_RAMP[0]),
                       t1=q(VAL_RAMP[1]), t_load=q(VAL_LOAD_STEP),
                       load_pu=jnp.asarray(point["load_pu"])[None],
                       k_d=k[0:1], k_q=k[1:2], k_R=k[2:3], k_psi=k[3:4],
                       k_noise=jnp.ones(1, sp.dtype), keys=key[None],
                       kind=jnp.full(1, 3), t_end=config.t_end)
    traj = simulate_set(lambda motor: space.observer(design, motor), drive,
                        pj.FOC.from_drive(drive), sset, T_s=config.T_s,
                        noise_std=config.noise_std, save_every=config.save_every)
    out = jax.tree_util.tree_map(lambda a: a[0], run_metrics(traj, config))
    # decimated traces for the figures (at most about `TRACE_SAMPLES` samples)
    stride = max(1, traj.t.shape[-1] // TRACE_SAMPLES)
    out["trace_theta_deg"] = jnp.degrees(traj.theta_err[0, ::stride])
    out["trace_w_err"] = (traj.w_m - traj.w_hat)[0, ::stride]
    return out


def operating_current(drive: pj.Drive, load_pu):
    """Controlled current $(i_d, i_q) = (0, \\tau_L / (k_\\tau\\psi_f))$ (A) for a load
    in p.u. of rated torque ($i_d = 0$)."""
    i_q = load_pu * drive.tau_rated / (drive.k_tau * drive.three_phase_motor.psi_f)
    return jnp.stack([jnp.zeros_like(i_q), i_q], -1)


def feasibility_point(design, config: CompareConfig, kind: str, point: dict) -> dict:
    """The generic analysis at one point of the grid at constant speed and current
    (`feasible`, `status`; see the module docstring)."""
    drive = config.drive()
    k = jnp.asarray(config.cases)[point["case"].astype(int)]
    obs = _space(config, kind).observer(
        design, motor=observer_model(drive, k[0], k[1], k[2], k[3]))
    op = OperatingPoint(point["speed_pu"] * float(drive.w_rated),
                        operating_current(drive, point["load_pu"]))
    plant = drive.three_phase_motor
    eq = obs.fast_equilibria(plant, op)
    if eq is None:
        tol = float(jnp.finfo(op.w_m.dtype).eps) ** 0.6
        eq = equilibria_traced(obs, plant, op, method="generic", n_grid=64, max_roots=8,
                               tol=tol)
    valid = eq.valid & (eq.status == 0)
    slots = jnp.arange(valid.shape[-1])
    principal = slots == eq.principal
    p_stable = jnp.any(principal & valid & eq.stable)
    other_stable = jnp.any(~principal & valid & eq.stable)
    feasible = (eq.status == 0) & p_stable & ~other_stable
    return dict(feasible=feasible, status=jnp.asarray(eq.status, jnp.int32))


# ---------------------------------------------------------------------------------------
# The job
# ---------------------------------------------------------------------------------------

class _Units:
    """Counts finished units of work and stops after `STOP_ENV` of them (tests)."""

    def __init__(self):
        v = os.environ.get(STOP_ENV)
        self.stop = int(v) if v else None
        self.done = 0

    def tick(self, *_):
        self.done += 1
        if self.stop is not None and self.done >= self.stop:
            raise CompareInterrupted(f"stopped after {self.done} units ({STOP_ENV})")


def _atomic_write(path: pathlib.Path, data: bytes):
    # one temporary name per process: under jax.distributed every process may write the
    # same (deterministic) file; os.replace makes the last complete write win
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _tuned(config: CompareConfig, name: str, folder: pathlib.Path, units, progress, log):
    """The tuned design of `name` (physical coordinates of the tuner's design space) and
    its record, from the cache or tuned now."""
    meta_path = folder / f"{name}.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        return (np.asarray(meta["x"], dtype=float) if meta["tuned"] else None), meta
    if config.tuner == "none":
        return None, dict(tuned=False, reason="no tuner (tuner = none)")
    folder.mkdir(parents=True, exist_ok=True)
    problem = config.tuning_problem(name)
    space = _space(config, name)
    log(f"tuning {name} ({config.tuner}, {problem.budget} closed-loop simulations) ...")
    t = time.perf_counter()
    ev = Evaluator(problem, space, training_set(problem))
    z0 = space.to_unconstrained(space.paper_point())
    res = STRATEGIES[config.tuner](ev, z0, budget=problem.budget,
                                   population=problem.population,
                                   key=jr.PRNGKey(config.seed),
                                   learning_rate=problem.learning_rate,
                                   clip_norm=problem.clip_norm, progress=progress)
    x = np.asarray(space.to_physical(jnp.asarray(res.z)))
    meta = dict(tuned=True, tuner=config.tuner, budget=problem.budget, sims=res.sims,
                objective="cvar (tuning.objective)",
                train_objective_paper=float(objective(ev.reference, ev.reference,
                                                      problem)[0]),
                train_objective_tuned=float(res.value), x=x.tolist(),
                coordinates=space.as_dict(x),
                design={k: float(v) for k, v in space.design(x).items()},
                seconds=time.perf_counter() - t)
    _atomic_write(meta_path, json.dumps(_clean(meta), indent=1).encode())
    units.tick()
    return x, meta


@eqx.filter_jit
def _replay(obs, u_ab, i_ab, T_s):
    return pj.replay(obs, u_ab=u_ab, i_ab=i_ab, T_s=T_s, theta0=0.0, w0=0.0)


def _cost(config: CompareConfig, name: str, folder: pathlib.Path, units) -> dict:
    """Compute cost of one observer step (us, replay at batch 1), cached."""
    path = folder / f"{name}.json"
    if path.is_file():
        return json.loads(path.read_text())
    drive = config.drive()
    obs = registry_observer(name, drive)
    n = int(round(config.t_end / config.T_s))
    t = np.arange(n) * config.T_s
    w = 0.5 * float(drive.w_rated)
    psi = float(drive.three_phase_motor.psi_f)
    u_ab = np.stack([-w * psi * np.sin(w * t), w * psi * np.cos(w * t)], -1)
    i_ab = np.zeros((n, 2))
    jax.block_until_ready(_replay(obs, u_ab, i_ab, config.T_s))
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(_replay(obs, u_ab, i_ab, config.T_s))
        best = min(best, time.perf_counter() - t0)
    out = dict(observer_us_per_step=1e6 * best / n, steps=n)
    folder.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, json.dumps(out).encode())
    units.tick()
    return out


def harmonic_sensitivity(design, config: CompareConfig, name: str):
    """Largest peak angle ripple per 1 % back-EMF harmonic (deg) over `harmonic_orders`
    and `harmonic_speeds_pu` (matched model, no load) from the linearisation
    (`pmsmjax.analysis.harmonic_ripple`), or `(None, reason)` where it is not finite (an
    unstable or resonant linearisation at one of the speeds)."""
    drive = config.drive()
    obs = _space(config, name).observer(design)
    orders = jnp.asarray(config.harmonic_orders)

    def one(s):
        op = OperatingPoint(s * float(drive.w_rated), jnp.zeros(2))
        return harmonic_ripple(obs, drive, op, orders)

    r = np.asarray(jax.vmap(one)(jnp.asarray(config.harmonic_speeds_pu)))
    if not np.all(np.isfinite(r)):
        return None, "harmonic_ripple returned non-finite values"
    return float(np.max(np.abs(r))), None


def aggregate(runs: dict, feas: dict | None, config: CompareConfig, grid) -> dict:
    """Per-observer metrics of one design from its per-run metrics `runs` and the
    analysis `feas` (numpy arrays over the grid, or None if not run; see the module
    docstring). Every value
    is a float, an int, a list or None with its reason in `flags`."""
    flags = {}
    lost = np.asarray(runs["lost_lock"]).reshape(-1)
    keep = ~lost
    static = np.asarray(runs["static_deg"]).reshape(-1)[keep]
    out = {"n_runs": int(lost.size), "lost_lock": int(lost.sum())}
    where = []
    for j in np.nonzero(lost)[0]:
        c = int(grid["case"][j])
        where.append(dict(speed_pu=float(grid["speed_pu"][j]),
                          load_pu=float(grid["load_pu"][j]),
                          **dict(zip(CASE_NAMES, config.cases[c]))))
    out["lost_lock_where"] = where

    def put(name, values, fn, why):
        v = values[np.isfinite(values)] if values.size else values
        if v.size == 0:
            out[name] = None
            flags[name] = why
        else:
            out[name] = float(fn(v))

    none_kept = "every run lost lock"
    put("static_worst_deg", static, lambda v: np.max(np.abs(v)), none_kept)
    put("static_rms_deg", static, lambda v: np.sqrt(np.mean(v ** 2)), none_kept)
    put("rms_worst_deg", np.asarray(runs["rms_deg"]).reshape(-1)[keep], np.max, none_kept)
    st = np.asarray(runs["settle_s"]).reshape(-1)[keep]
    out["n_unsettled"] = int(np.sum(~np.isfinite(st)))
    why = none_kept if st.size == 0 else "no run settled within the band"
    put("settle_worst_s", st, np.max, why)
    put("settle_median_s", st, np.median, why)
    nz = np.asarray(runs["noise_rad_s"]).reshape(-1)[keep]
    put("noise_median_rad_s", nz, np.median, none_kept)
    put("noise_worst_rad_s", nz, np.max, none_kept)
    if feas is None:
        out["feasible_fraction"] = out["analysis_failed"] = None
        flags["feasible_fraction"] = flags["analysis_failed"] = \
            "the analysis was not run (analysis = False)"
    else:
        f = np.asarray(feas["feasible"]).reshape(-1)
        out["feasible_fraction"] = float(np.mean(f))
        out["analysis_failed"] = int(np.sum(np.asarray(feas["status"]).reshape(-1) < 0))
    out["flags"] = flags
    return out


def _sweep(fn, grid, out_dir, config, metadata, progress, units, batch_size):
    return run_sweep(fn, grid, out_dir=out_dir, chunk_size=config.chunk_size,
                     batch_size=batch_size, metadata=metadata,
                     progress=progress and jax.process_index() == 0, resume=True,
                     on_chunk_done=units.tick, keep_chunks=False)


class _Context:
    """What every observer's part of the job shares (see `observer_entry`)."""

    def __init__(self, config, out, sweeps, grid, progress, log, batch_size):
        self.config, self.out, self.sweeps, self.grid = config, out, sweeps, grid
        self.progress, self.log, self.batch_size = progress, log, batch_size

    def entry_path(self, name: str) -> pathlib.Path:
        return self.out / "observers" / f"{name}.json"


def observer_entry(ctx: _Context, name: str, units, *, class_name: str | None = None):
    """One observer's part of the job: tune (or load the tuned design), measure the cost
    per step, run both designs' sweeps and aggregate. Returns `(entry, timing)` and keeps
    both in `OUT/observers/NAME.json`, so that a resumed job (or the parent of worker
    processes, `jobs`) reads them instead of computing them again."""
    path = ctx.entry_path(name)
    if path.is_file():
        rec = json.loads(path.read_text())
        return rec["entry"], rec["timing"]
    config, out, sweeps, grid = ctx.config, ctx.out, ctx.sweeps, ctx.grid
    progress, log, batch_size = ctx.progress, ctx.log, ctx.batch_size
    n_runs = len(grid["case"])
    tim = {}
    design_t, meta = _tuned(config, name, out / "tuned", units, progress, log)
    tim["tuning_s"] = meta.pop("seconds", None)
    tim.update(_cost(config, name, out / "cost", units))
    # measured on this machine: differs between any two runs (`TIMING_KEYS`)
    entry = {"class": class_name or observer_class(name).__name__, "designs": {},
             "tuning": meta, "observer_us_per_step": tim["observer_us_per_step"]}
    for dname, design in (("paper", None), ("tuned", design_t)):
        if dname == "tuned" and design is None:
            entry["designs"][dname] = dict(flags={"all": "tuned design not available: "
                                                  + meta.get("reason", "")})
            continue
        cols = _design_columns(design)
        f_runs, f_feas = _sweep_fns(config, name, len(cols))
        sweep_dir = sweeps / name / dname
        md = dict(observer=name, design=dname, config=config.fingerprint())
        log(f"{name}, {dname} design: {n_runs} runs ...")
        t = time.perf_counter()
        g = SweepGrid({**grid, **{k: np.full(n_runs, v) for k, v in cols.items()}},
                      shape=grid.shape, axes=grid.axes)
        runs = _sweep(f_runs, g, sweep_dir / "runs", config, md, progress, units,
                      batch_size)
        tim[f"{dname}_runs_s"] = time.perf_counter() - t
        t = time.perf_counter()
        agrid = {k: v for k, v in g.items() if k != "index"}
        feas = (_sweep(f_feas, agrid, sweep_dir / "analysis", config, md, progress,
                       units, batch_size) if config.analysis else None)
        tim[f"{dname}_analysis_s"] = time.perf_counter() - t
        m = aggregate(runs, feas, config, grid)
        t = time.perf_counter()
        h, why = harmonic_sensitivity(design, config, name)
        tim[f"{dname}_harmonic_s"] = time.perf_counter() - t
        m["harmonic_deg_per_pct"] = h
        if why:
            m["flags"]["harmonic_deg_per_pct"] = why
        entry["designs"][dname] = m
    entry, tim = _clean(entry), _clean(tim)
    if jax.process_index() == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(path, json.dumps(dict(entry=entry, timing=tim), indent=1).encode())
    return entry, tim


def _run_workers(ctx: _Context, names: list, jobs: int):
    """Run `observer_entry` for `names` in `jobs` worker processes at a time (`python -m
    tuning.compare.worker`); each writes `OUT/observers/NAME.json` and its log to
    `OUT/logs/NAME.log`. Compilation, which dominates a small comparison, is per observer
    and runs on one or two cores per process, so the observers compile side by side."""
    import subprocess
    import sys

    if not names:
        return
    logs = ctx.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "tuning.compare.worker", "--out", str(ctx.out),
           "--sweep-dir", str(ctx.sweeps)]
    if ctx.batch_size:
        cmd += ["--batch-size", str(ctx.batch_size)]
    ctx.log(f"{len(names)} observers in {min(jobs, len(names))} worker processes (logs: "
            f"{logs}) ...")
    bar = _observer_bar(len(names), ctx.progress)
    queue, running, failed = list(names), {}, []
    try:
        while queue or running:
            while queue and len(running) < jobs:
                n = queue.pop(0)
                f = open(logs / f"{n}.log", "w")
                running[n] = (subprocess.Popen(cmd + ["--observer", n], stdout=f,
                                               stderr=subprocess.STDOUT), f)
            time.sleep(0.2)
            for n, (proc, f) in list(running.items()):
                if proc.poll() is None:
                    continue
                f.close()
                del running[n]
                if proc.returncode != 0:
                    failed.append(n)
                bar.update(1)
                bar.set_postfix_str(n)
    finally:
        for proc, f in running.values():
            proc.kill()
            f.close()
        bar.close()
    if failed:
        raise RuntimeError(f"worker processes failed for {', '.join(failed)}; see "
                           f"{logs}/<observer>.log (the other observers' results are kept: "
                           f"run the job again to continue)")


def _observer_bar(n, progress):
    from tqdm.auto import tqdm

    return tqdm(total=n, desc="observers", unit="obs", disable=not progress)



def run_comparison(config: CompareConfig, out, *, progress: bool = True, log=print,
                   restart: bool = False, plot: bool = False, sweep_dir=None,
                   batch_size: int | None = None, jobs: int = 1) -> dict:
    """Run the comparison into the job folder `out` and return the summary (the content
    of `comparison.json`). Resumable: tuned designs, cost measurements and every sweep
    chunk are kept in `out`, and a second call continues where the first stopped.
    `restart`: start over (`ValueError` if `out` holds a job of another configuration
    unless `restart`). `plot`: also write the figures (`tuning.compare.plots`).
    `sweep_dir`: folder of the sweeps (default `out/sweeps`: one sweep of the runs and
    one of the analysis per observer and design, `NAME/DESIGN/runs`, `.../analysis`);
    `batch_size`: of `run_sweep` (bitwise the same results on any device count).
    `jobs`: observers computed side by side in this many worker processes (1: all in
    this process; not with `jax.distributed`). The results do not depend on it.

    Under `jax.distributed` every process runs this function (the sweeps are sharded
    over the devices of all processes, the tuning is repeated in each, deterministic);
    only process 0 writes the outputs."""
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"`run_comparison(jobs=...)` must be an int >= 1; got {jobs!r}.")
    if jobs > 1 and jax.process_count() > 1:
        raise ValueError("`run_comparison(jobs=...)` > 1 cannot be combined with "
                         "jax.distributed (several processes already share the work); "
                         "give jobs=1.")
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    job = out / "job.json"
    fp = config.fingerprint()
    if job.is_file() and not restart:
        old = json.loads(job.read_text())
        if old.get("fingerprint") != fp:
            raise ValueError(f"{out} holds a comparison with another configuration; give "
                             f"another --out or --restart.")
    sweeps = out / "sweeps" if sweep_dir is None else pathlib.Path(sweep_dir)
    if restart:
        import shutil

        for sub in (out / "tuned", out / "cost", out / "observers", out / "logs", sweeps):
            shutil.rmtree(sub, ignore_errors=True)
    _atomic_write(job, json.dumps(dict(format=FORMAT, fingerprint=fp,
                                       config=config.to_dict()), indent=1).encode())
    log = log or (lambda msg: None)
    units = _Units()
    t_start = time.perf_counter()
    ok, skipped = applicable_observers(config)
    grid = config.grid(index=True)
    n_runs = len(grid["case"])
    steps = int(round(config.t_end / config.T_s))
    log(f"comparison on {config.motor}: {len(ok)} observers x {len(DESIGNS)} designs x "
        f"{n_runs} runs ({2 * len(config.speeds_pu)} speeds x {len(config.loads_pu)} loads "
        f"x {len(config.cases)} mismatch cases) of {steps} steps")
    observers, timing = {}, {"observers": {}}
    ctx = _Context(config, out, sweeps, grid, progress, log, batch_size)
    if jobs > 1:
        _run_workers(ctx, [n for n in ok if not ctx.entry_path(n).is_file()], jobs)
    for name in ok:
        entry, tim = observer_entry(ctx, name, units, class_name=ok[name])
        observers[name] = entry
        timing["observers"][name] = tim
    timing["wall_s"] = time.perf_counter() - t_start
    timing["runs_per_design"] = n_runs
    timing["steps_per_run"] = steps
    timing["devices"] = [str(d) for d in jax.devices()]
    timing["processes"] = jax.process_count()
    summary = dict(format=FORMAT, motor=config.motor, config=config.to_dict(),
                   grid=dict(speeds_pu=sorted(set(grid.axes["speed_pu"].tolist())),
                             loads_pu=list(config.loads_pu),
                             cases=[dict(zip(CASE_NAMES, c)) for c in config.cases],
                             n_runs=n_runs),
                   observers=observers, skipped=skipped)
    summary = _clean(summary)
    writer = jax.process_index() == 0
    if writer:
        _atomic_write(out / "comparison.json", json.dumps(summary, indent=1).encode())
        _atomic_write(out / "comparison.md", markdown(summary).encode())
        _atomic_write(out / "timing.json", json.dumps(_clean(timing), indent=1).encode())
    summary["timing"] = _clean(timing)
    if plot and writer:
        from .plots import plot_comparison

        plot_comparison(summary, out, sweeps)
    return summary


# ---------------------------------------------------------------------------------------
# comparison.md
# ---------------------------------------------------------------------------------------

COLUMNS = (
    ("static_worst_deg", "worst static error (deg)", "{:.2f}"),
    ("static_rms_deg", "RMS static error (deg)", "{:.2f}"),
    ("rms_worst_deg", "worst run RMS error (deg)", "{:.2f}"),
    ("settle_worst_s", "worst settling (s)", "{:.3f}"),
    ("noise_median_rad_s", "median speed noise (rad/s)", "{:.3g}"),
    ("lost_lock", "lost lock (runs)", "{}"),
    ("feasible_fraction", "feasible (analysis)", "{:.0%}"),
    ("harmonic_deg_per_pct", "harmonic ripple (deg / %)", "{:.3g}"),
)


def _fmt(v, f):
    return "n/a" if v is None else f.format(v)


def markdown(summary: dict) -> str:
    """`comparison.md`: the table (observers as rows, paper and tuned design) and the
    definitions of the metrics."""
    c = summary["config"]
    g = summary["grid"]
    lines = [f"# Observer comparison on {summary['motor']}", "",
             f"{g['n_runs']} closed-loop, speed-controlled sensorless runs per observer and "
             f"design: speeds {', '.join(f'{s:g}' for s in g['speeds_pu'])} p.u., loads "
             f"{', '.join(f'{x:g}' for x in g['loads_pu'])} p.u. (step at 0.6 t_end), "
             f"{len(g['cases'])} observer-model mismatch cases (k_d, k_q, k_R, k_psi), "
             f"current noise {c['noise_std']:g} A, T_s = {c['T_s']:g} s, "
             f"t_end = {c['t_end']:g} s.", "",
             "| observer | design | " + " | ".join(h for _, h, _ in COLUMNS)
             + " | observer step (us) |",
             "|---|---|" + "---|" * (len(COLUMNS) + 1)]
    for name, e in summary["observers"].items():
        cost = _fmt(e.get("observer_us_per_step"), "{:.3g}")
        for dname in DESIGNS:
            m = e["designs"].get(dname, {})
            cells = [_fmt(m.get(k), f) for k, _, f in COLUMNS]
            lines.append(f"| {name} | {dname} | " + " | ".join(cells) + f" | {cost} |")
    lines += ["", "n/a: not computed; the reason is in `flags` in comparison.json."]
    if summary["skipped"]:
        lines += ["", "Not applicable to this motor: " + "; ".join(
            f"{k} ({v})" for k, v in summary["skipped"].items())]
    flags = sorted({f"{n}/{d}: {k}: {v}" for n, e in summary["observers"].items()
                    for d, m in e["designs"].items() for k, v in m.get("flags", {}).items()})
    if flags:
        lines += ["", "## Flags", ""] + [f"- {f}" for f in flags]
    lines += ["", "## Definitions", "",
              f"- static error: mean angle error (true minus estimate) over the last "
              f"{STATIC_WINDOW:.0%} of each run; worst = largest magnitude, RMS over the "
              f"runs that kept lock;",
              "- run RMS error: RMS of the angle error over the whole run;",
              f"- settling: from the start of the speed ramp (0.1 t_end) until the angle "
              f"error stays within {c['settle_band_deg']:g} deg of its static value;",
              "- speed noise: standard deviation of the speed-estimate error over the "
              "static window (rad/s, electrical);",
              f"- lost lock: |angle error| above {c['lock_deg']:g} deg, or a diverged or "
              "non-finite run (these runs are left out of the other columns);",
              "- feasible: fraction of the grid (constant speed and current) where the "
              "generic equilibrium analysis finds the designed equilibrium stable and no "
              "other stable equilibrium;",
              "- harmonic ripple: largest peak angle-error ripple per 1 % back-EMF "
              "harmonic (orders " + ", ".join(str(o) for o in c["harmonic_orders"])
              + ");",
              "- observer step: compute cost of one observer step (replay at batch 1, "
              "best of three; a measurement of this machine);",
              "- tuned: the existing tuner from the paper design on a small training "
              f"problem ({c['tuner']}, {c['tune_steps']} steps).", ""]
    return "\n".join(lines)


__all__ = ["CASES", "CompareConfig", "CompareInterrupted", "aggregate",
           "applicable_observers", "feasibility_point", "markdown", "run_comparison",
           "run_metrics", "run_point"]
