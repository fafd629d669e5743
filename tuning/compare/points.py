r"""What the comparison's sweeps compute at one point of the common grid (`run_point`, a
closed-loop run; `feasibility_point`, the equilibrium analysis) and the harmonic
sensitivity of a design.

**Per-run metrics** (`run_metrics`): the library's one definition (`pmsmjax.run_metrics`,
the tuner's too; $\tilde\theta = \theta - \hat\theta$ wrapped, deg, and
$\tilde\omega = \omega - \hat\omega$, rad/s, on the saved samples):

- `static_deg`: the static angle error, the mean of $\tilde\theta$ over the *static
  window* (`pmsmjax.static_window`: the last `pmsmjax.STATIC_WINDOW` = 20 % of the run,
  by time, after the ramp and the load step);
- `rms_deg`: RMS of $\tilde\theta$ over the whole run (what the ramp, the load step, the
  mismatch and the noise cause together);
- `max_abs_deg`: largest $|\tilde\theta|$ over the run;
- `settle_s`: settling time, from the start of the ramp ($0.1\,t_{end}$) until
  $|\tilde\theta - \tilde\theta_{static}| \le$ `settle_band_deg` for good; NaN if the
  last sample is outside the band (never settled);
- `noise_rad_s`: speed-estimate noise, the standard deviation of $\tilde\omega$ over the
  static window;
- `lost_lock`: the run lost lock, by the library's one definition (`pmsmjax.lock_status`
  with `start_locked`: every run starts with the observer on the true angle): the mean
  $|\tilde\theta|$ over any 10 ms of the run above `lock_deg`, default 45 deg, or the run
  diverged or produced a non-finite sample, which counts as 180 deg);
- `t_lost`: when it lost lock (s, the same definition's; NaN if it kept lock).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import harmonic_ripple
from pmsmjax.observers import OperatingPoint

from ..design_space import DesignSpace
from ..scenarios import (
    VAL_LOAD_STEP,
    VAL_RAMP,
    ScenarioSet,
    designed_feasible,
    observer_model,
    operating_current,
    simulate_set,
)
from .config import TRACE_SAMPLES, CompareConfig


#: The per-run metrics of the comparison (`run_metrics`), the outputs of its run sweeps.
RUN_METRICS = ("static_deg", "rms_deg", "max_abs_deg", "settle_s", "noise_rad_s",
               "lost_lock", "t_lost")


def run_metrics(traj: pj.Trajectory, config: CompareConfig) -> dict:
    """Per-run metrics of a (batched) trajectory of the common grid (module docstring):
    `pmsmjax.run_metrics` with the comparison's lock threshold, settling band and the
    ramp's start as the start of the settling time."""
    m = pj.run_metrics(traj, lock_deg=config.lock_deg,
                       settle_from=VAL_RAMP[0] * config.t_end,
                       settle_band_deg=config.settle_band_deg)
    return {k: m[k] for k in RUN_METRICS}


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


def phase_times(config: CompareConfig) -> tuple[float, float, float]:
    """`(t0, t1, t_load)` (s) of every run of the grid: the ramp over `VAL_RAMP` and the
    load step at `VAL_LOAD_STEP` (fractions of `t_end`), on the sampling grid."""
    return tuple(round(f * config.t_end / config.T_s) * config.T_s
                 for f in (*VAL_RAMP, VAL_LOAD_STEP))


def _point_set(config: CompareConfig, point: dict) -> ScenarioSet:
    """The one run of grid point `point` as a `ScenarioSet` (see `run_point`)."""
    k = jnp.asarray(config.cases)[point["case"].astype(int)]
    sp = jnp.asarray(point["speed_pu"])[None]
    key = jr.fold_in(jr.PRNGKey(config.seed), point["index"].astype(jnp.uint32))
    t0, t1, t_load = (jnp.full(1, t) for t in phase_times(config))
    return ScenarioSet(s0=config.start_frac * sp, s1=sp, t0=t0, t1=t1, t_load=t_load,
                       load_pu=jnp.asarray(point["load_pu"])[None],
                       k_d=k[0:1], k_q=k[1:2], k_R=k[2:3], k_psi=k[3:4],
                       k_noise=jnp.ones(1, sp.dtype), keys=key[None],
                       kind=jnp.full(1, 3), t_end=config.t_end)


def sensored_point(config: CompareConfig, point: dict) -> dict:
    """The run of grid point `point` (as `run_point`'s: the same controller, scenario and
    noise) with the sensored observer (the true angle and speed): `lowest_speed_pu`, the
    lowest speed magnitude the rotor reaches in it (p.u. of rated, every sample). The
    low-speed rule of the tuner (`tuning.scenarios.low_speed_runs`) on the common grid:
    a point where even this drive turns slower than an observer class's declared limit
    (`low_speed_limit_pu`) is beyond that class."""
    drive = config.drive()
    traj = simulate_set(lambda motor: pj.SensoredObserver(), drive,
                        pj.FOC.from_drive(drive), _point_set(config, point), T_s=config.T_s,
                        noise_std=config.noise_std, save_every=1)
    return {"lowest_speed_pu": jnp.min(jnp.abs(traj.w_m[0])) / float(drive.w_rated)}


def run_point(design, config: CompareConfig, kind: str, point: dict) -> dict:
    """Simulate one point of the common grid (`tuning.scenarios.simulate_set`, the runs
    of the tuner's validation set) with the design `design` (physical coordinates of the
    tuner's design space; None: the paper's) and return its `run_metrics`. `point`:
    `speed_pu` (signed), `load_pu`, `case` (index into `config.cases`), `index` (of the
    noise key)."""
    drive = config.drive()
    space = _space(config, kind)
    traj = simulate_set(lambda motor: space.observer(design, motor), drive,
                        pj.FOC.from_drive(drive), _point_set(config, point), T_s=config.T_s,
                        noise_std=config.noise_std, save_every=config.save_every,
                        speed_from_angle=config.speed_from_angle)
    out = jax.tree_util.tree_map(lambda a: a[0], run_metrics(traj, config))
    # decimated traces for the figures (at most about `TRACE_SAMPLES` samples)
    stride = max(1, traj.t.shape[-1] // TRACE_SAMPLES)
    out["trace_theta_deg"] = jnp.degrees(traj.theta_err[0, ::stride])
    out["trace_w_err"] = (traj.w_m - traj.w_hat)[0, ::stride]
    return out


def feasibility_point(design, config: CompareConfig, kind: str, point: dict) -> dict:
    """The generic analysis at one point of the grid at constant speed and current
    (`feasible`, `status`; see the module docstring)."""
    drive = config.drive()
    k = jnp.asarray(config.cases)[point["case"].astype(int)]
    obs = _space(config, kind).observer(
        design, motor=observer_model(drive, k[0], k[1], k[2], k[3]))
    return designed_feasible(obs, drive, point["speed_pu"], point["load_pu"])


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


__all__ = ["RUN_METRICS", "feasibility_point", "harmonic_sensitivity", "operating_current",
           "phase_times", "run_metrics", "run_point", "sensored_point"]
