r"""Optimisers for the gain schedule: optax Adam, optimistix BFGS and Levenberg-Marquardt,
and a gradient-free random search with the same simulation budget.

All work on the tuned part of a tunable design (`tuning.AbstractDesign`: the
speed-scheduled `GainSchedule` or the generic `ConstantDesign`; `eqx.partition` with
`filter_spec(design, config.tuned)`), i.e. on unconstrained variables, and return a
`TuningResult`. Every loop

- compiles its step once (`eqx.filter_jit`; the Adam step is wrapped in
  `eqx.debug.assert_max_traces(max_traces=1)`, so an accidental recompilation raises);
- computes, before each step and outside the differentiated function, the equilibria
  that start the stability penalty's Newton steps (`objectives.equilibria`);
- shows a tqdm progress bar with the current and best loss;
- keeps the best iterate and stops early when the best loss improved by less than
  `min_improvement` (relative) over the last `patience` steps; for the "no_regression"
  objective only iterates whose training losses all stay within `regression_tol` of the
  reference (the starting design's, unless `reference` is given) can be the best, so
  the result never regresses a training scenario beyond the tolerance;
- is deterministic: the noise keys come from `config.seed`, the random search draws from
  `jax.random.PRNGKey(seed)`, and nothing else is random.

Counting: one evaluation of the objective simulates every scenario once, so
`n_simulations` grows by the number of scenarios per step for every method (a gradient
step costs about 3.5x the wall time of a forward evaluation on the default problem; the
benchmark reports both).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import optimistix as optx
from tqdm import tqdm

from ._parametrise import AbstractDesign, filter_spec
from .objectives import (
    Metrics,
    equilibria,
    evaluate,
    loss,
    objective_value,
    residuals,
    within_tolerance,
)
from .scenarios import ScenarioSet, TuningConfig


class TuningResult(eqx.Module):
    """Output of an optimiser.

    - `value`: the best design found (lowest loss among the evaluated iterates; the same
      type as the starting design, e.g. a `GainSchedule` or a `ConstantDesign`).
    - `loss`: its objective value.
    - `metrics`: its per-scenario `Metrics` on the training scenarios.
    - `result`: a message: why the loop stopped.
    - `stats`: per-evaluation histories (numpy arrays): `loss` (objective of the iterate
      evaluated at that step), `best` (running minimum), `n_simulations` (cumulative
      closed-loop runs), `wall_time_s` (cumulative seconds since the loop started,
      compilation included), `wall_time_warm_s` (the same with the first evaluation
      counted as a typical one, i.e. without compilation), plus `compile_time_s`,
      `steps`, `method`, `stopped_early`.
    """

    value: AbstractDesign
    loss: float
    metrics: Metrics
    result: str
    stats: dict


class _Tracker:
    """Best iterate, histories, progress bar and early stopping, shared by the loops."""

    def __init__(self, method, steps, n_scen, config: TuningConfig, progress: bool,
                 reference=None):
        self.method, self.n_scen, self.config = method, n_scen, config
        self.reference = None if reference is None else np.asarray(reference)
        self.within = []
        self.best, self.best_value, self.best_metrics = None, np.inf, None
        self.losses, self.bests, self.sims, self.times = [], [], [], []
        self.t0 = time.perf_counter()
        self.bar = tqdm(total=steps, desc=f"{method:>6}", disable=not progress, leave=True,
                        dynamic_ncols=True)

    def record(self, params, value, metrics) -> bool:
        """Record one evaluation; return True to stop early (the best loss improved by
        less than `min_improvement` (relative) over the last `patience` evaluations)."""
        value = float(value)
        self.losses.append(value)
        self.sims.append((len(self.sims) + 1) * self.n_scen)
        self.times.append(time.perf_counter() - self.t0)
        ok = self.admissible(metrics)
        self.within.append(ok)
        if np.isfinite(value) and value < self.best_value and ok:
            self.best, self.best_value, self.best_metrics = params, value, metrics
        self.bests.append(self.best_value)
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{value:.4g}", best=f"{self.best_value:.4g}")
        p = self.config.patience
        if p <= 0 or len(self.bests) <= p:
            return False
        before, now = self.bests[-1 - p], self.bests[-1]
        if not np.isfinite(now):
            return False
        return before - now < self.config.min_improvement * abs(now)

    def admissible(self, metrics) -> bool:
        """Whether an iterate may be the best: always, except for the "no_regression"
        objective, where every training loss must stay within `regression_tol` of the
        reference."""
        if self.reference is None or self.config.objective != "no_regression":
            return True
        return within_tolerance(metrics.loss, self.reference, self.config.regression_tol)

    def finish(self, static, message, compile_time, stopped_early) -> TuningResult:
        self.bar.close()
        if self.best is None:
            raise RuntimeError(f"{self.method}: no admissible design was evaluated: every "
                               "loss was non-finite (the configuration makes every run "
                               "diverge) or, for the 'no_regression' objective, every "
                               "design regressed a scenario beyond the tolerance against "
                               "the given reference.")
        times = np.asarray(self.times)
        steps = np.diff(times, prepend=0.0)
        if steps.size > 1:  # the first evaluation's compilation replaced by a typical step
            steps[0] = np.median(steps[1:])
        stats = dict(loss=np.asarray(self.losses), best=np.asarray(self.bests),
                     n_simulations=np.asarray(self.sims), wall_time_s=times,
                     wall_time_warm_s=np.cumsum(steps),
                     within_tolerance=np.asarray(self.within, dtype=bool),
                     compile_time_s=float(compile_time), steps=len(self.losses),
                     method=self.method, stopped_early=bool(stopped_early))
        return TuningResult(value=eqx.combine(self.best, static), loss=self.best_value,
                            metrics=self.best_metrics, result=message, stats=stats)


def _reference(schedule, config, scenarios, reference):
    """The per-scenario losses the "no_regression" objective compares with: `reference`
    if given, else the starting design's (None for the other objectives)."""
    if config.objective != "no_regression":
        return None
    if reference is None:
        reference = evaluate(schedule, config, scenarios, objective="robust")[1].loss
    return jnp.asarray(reference)


def _eqs(schedule, config, scenarios):
    return equilibria(schedule, config, scenarios) if config.w_stab > 0 else None


def _check_schedule(schedule):
    if not isinstance(schedule, AbstractDesign):
        raise ValueError(f"the optimisers tune a `tuning.AbstractDesign` (`GainSchedule`, "
                         f"`ConstantDesign`); got {type(schedule).__name__}.")


def _optimiser(lr):
    return optax.chain(optax.zero_nans(), optax.adam(lr))


def _signature(tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return treedef, tuple((np.shape(x), str(np.asarray(x).dtype)) for x in leaves)


_ADAM_STEPS: dict = {}


def _adam_step(config: TuningConfig, diff, n_scen: int):
    """The compiled Adam step for this configuration and problem shape (cached, so that
    restricted runs and repeated calls reuse one compilation)."""
    key = (config, _signature(diff), n_scen)
    if key not in _ADAM_STEPS:
        @eqx.filter_jit
        @eqx.debug.assert_max_traces(max_traces=1)
        def step(diff, static, scenarios, opt_state, eqs, mask, lr, ref):
            def f(d):
                return loss(eqx.combine(d, static), config, scenarios, eqs, reference=ref)

            (value, metrics), grads = eqx.filter_value_and_grad(f, has_aux=True)(diff)
            updates, opt_state = _optimiser(lr).update(grads, opt_state, diff)
            # leaves outside the restricted set do not move (mask from a filter spec)
            updates = jax.tree_util.tree_map(lambda u, m: u * m, updates, mask)
            return eqx.apply_updates(diff, updates), opt_state, value, metrics

        _ADAM_STEPS[key] = step
    return _ADAM_STEPS[key]


def adam(schedule: AbstractDesign, config: TuningConfig, scenarios: ScenarioSet, *,
         steps: int | None = None, learning_rate: float | None = None,
         tuned=None, progress: bool = True, reference=None) -> TuningResult:
    """Adam (optax) on the unconstrained tuned leaves, `config.steps` steps.

    The schedule is partitioned with `filter_spec(schedule, config.tuned)`; `tuned` (a
    subset of `config.tuned`, default all of it) restricts which of those leaves move
    (the others are masked by a PyTree built from `filter_spec(schedule, tuned)`), so a
    restricted run reuses the same compiled step. Non-finite gradient entries (a
    diverged run's branch) are zeroed (`optax.zero_nans`). `reference`: the per-scenario
    losses of the "no_regression" objective (default: the starting design's).
    """
    _check_schedule(schedule)
    steps = config.steps if steps is None else steps
    lr = config.learning_rate if learning_rate is None else learning_rate
    tuned = config.tuned if tuned is None else tuple(tuned)
    extra = [n for n in tuned if n not in config.tuned]
    if extra:
        raise ValueError(f"`adam(tuned=...)` must be a subset of `config.tuned` "
                         f"{config.tuned}; got {', '.join(extra)}.")
    spec = filter_spec(schedule, config.tuned)
    diff, static = eqx.partition(schedule, spec)
    sub = eqx.filter(filter_spec(schedule, tuned), spec)
    mask = jax.tree_util.tree_map(lambda d, m: jnp.full_like(d, float(m)), diff, sub)
    opt_state = _optimiser(lr).init(diff)
    step = _adam_step(config, diff, scenarios.n)
    lr = jnp.asarray(lr, jnp.float64)

    name = "adam" if tuned == config.tuned else "adam*"
    ref = _reference(schedule, config, scenarios, reference)
    tr = _Tracker(name, steps, scenarios.n, config, progress, ref)
    compile_time, stopped = 0.0, False
    message = f"finished {steps} steps"
    for k in range(steps):
        eqs = _eqs(eqx.combine(diff, static), config, scenarios)
        t = time.perf_counter()
        new_diff, opt_state, value, metrics = step(diff, static, scenarios, opt_state, eqs,
                                                   mask, lr, ref)
        value = float(value)
        if k == 0:
            compile_time = time.perf_counter() - t
        if tr.record(diff, value, metrics):
            stopped, message = True, (f"early stop after {k + 1} steps: the best loss "
                                      f"improved by less than {config.min_improvement:g} "
                                      f"(relative) in {config.patience} steps")
            break
        diff = new_diff
    return tr.finish(static, message, compile_time, stopped)


_OPTX_FNS: dict = {}


def _optx_fns(name, solver, fn, config, static, diff, scenarios, eqs, ref, f_struct):
    """Compiled `init` and `step` of an optimistix solver for this problem (cached per
    configuration and problem shape, like the Adam step)."""
    key = (name, config, _signature(diff), _signature(static), scenarios.n)
    if key in _OPTX_FNS:
        return _OPTX_FNS[key]

    def wrapped(d, args):
        scen, eqs_, ref_ = args
        return fn(eqx.combine(d, static), config, scen, eqs_, reference=ref_)

    aux_struct = eqx.filter_eval_shape(wrapped, diff, (scenarios, eqs, ref))[1]
    options, tags = {}, frozenset()

    @eqx.filter_jit
    def init(y, args):
        return solver.init(wrapped, y, args, options, f_struct, aux_struct, tags)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def step(y, state, args):
        # one evaluation of fn (value and derivative) at the solver's trial point; the
        # returned y is the last accepted point and `state.aux` its metrics
        y_new, state, _ = solver.step(wrapped, y, args, options, state, tags)
        done, result = solver.terminate(wrapped, y_new, args, options, state, tags)
        return y_new, state, state.aux, done, result

    _OPTX_FNS[key] = (init, step)
    return init, step


def _optx_loop(name, solver, fn, schedule, config, scenarios, steps, progress, f_struct,
               tuned, reference):
    tuned = config.tuned if tuned is None else tuple(tuned)
    spec = filter_spec(schedule, tuned)
    diff, static = eqx.partition(schedule, spec)
    eqs = _eqs(schedule, config, scenarios)
    ref = _reference(schedule, config, scenarios, reference)
    init, step = _optx_fns(name, solver, fn, config, static, diff, scenarios, eqs, ref,
                           f_struct)
    tr = _Tracker(name, steps, scenarios.n, config, progress, ref)
    state = init(diff, (scenarios, eqs, ref))
    y = diff
    compile_time, stopped, message = 0.0, False, f"finished {steps} steps"
    for k in range(steps):
        t = time.perf_counter()
        y_new, state, aux, done, result = step(y, state, (scenarios, eqs, ref))
        value = float(objective_value(aux.loss, config, ref))  # at the accepted point y_new
        if k == 0:
            compile_time = time.perf_counter() - t
        early = tr.record(y_new, value, aux)
        if not np.isfinite(value):
            message = f"stopped after {k + 1} steps: non-finite loss"
            break
        if bool(done):
            message = (f"converged after {k + 1} steps" if result == optx.RESULTS.successful
                       else f"stopped after {k + 1} steps: {optx.RESULTS[result]}")
            break
        if early:
            stopped, message = True, (f"early stop after {k + 1} steps: the best loss "
                                      f"improved by less than {config.min_improvement:g} "
                                      f"(relative) in {config.patience} steps")
            break
        y = y_new
        eqs = _eqs(eqx.combine(y, static), config, scenarios)
    return tr.finish(static, message, compile_time, stopped)


def bfgs(schedule: AbstractDesign, config: TuningConfig, scenarios: ScenarioSet, *,
         steps: int | None = None, tuned=None, progress: bool = True,
         reference=None) -> TuningResult:
    """BFGS (optimistix) on the objective, stepped manually for progress and history."""
    _check_schedule(schedule)
    steps = config.steps if steps is None else steps
    solver = optx.BFGS(rtol=1e-6, atol=1e-8)
    f_struct = jax.ShapeDtypeStruct((), jnp.float64)
    return _optx_loop("bfgs", solver, loss, schedule, config, scenarios, steps, progress,
                      f_struct, tuned, reference)


def levenberg_marquardt(schedule: AbstractDesign, config: TuningConfig,
                        scenarios: ScenarioSet, *, steps: int | None = None, tuned=None,
                        progress: bool = True, reference=None) -> TuningResult:
    """Levenberg-Marquardt (optimistix) on `objectives.residuals` (forward-mode
    Jacobian: one column per tuned variable)."""
    _check_schedule(schedule)
    steps = config.steps if steps is None else steps
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
    n_res = scenarios.n if config.objective == "average" else 1
    f_struct = jax.ShapeDtypeStruct((n_res,), jnp.float64)
    return _optx_loop("lm", solver, residuals, schedule, config, scenarios, steps, progress,
                      f_struct, tuned, reference)


def random_search(schedule: AbstractDesign, config: TuningConfig, scenarios: ScenarioSet, *,
                  n_designs: int, box: float = 3.0, seed: int | None = None, tuned=None,
                  progress: bool = True, reference=None) -> TuningResult:
    """Gradient-free baseline: `n_designs` designs, the first one `schedule` itself, the
    others uniform in the unconstrained box `[-box, box]` of every tuned variable (the
    whole physical box but its outer 5% in the logistic map for `box = 3`), drawn from
    `PRNGKey(seed)` (default `config.seed`)."""
    _check_schedule(schedule)
    if n_designs < 1:
        raise ValueError(f"`random_search(n_designs=...)` must be >= 1; got {n_designs}.")
    if not box > 0:
        raise ValueError(f"`random_search(box=...)` must be > 0; got {box!r}.")
    spec = filter_spec(schedule, config.tuned if tuned is None else tuned)
    diff, static = eqx.partition(schedule, spec)
    flat, unravel = jax.flatten_util.ravel_pytree(diff)
    key = jr.PRNGKey(config.seed if seed is None else seed)
    z = jr.uniform(key, (n_designs, flat.shape[0]), flat.dtype, -box, box)
    z = z.at[0].set(flat)
    ref = _reference(schedule, config, scenarios, reference)
    tr = _Tracker("random", n_designs, scenarios.n, config, progress, ref)
    compile_time, stopped, message = 0.0, False, f"evaluated {n_designs} designs"
    for k in range(n_designs):
        d = unravel(z[k])
        t = time.perf_counter()
        value, metrics = evaluate(eqx.combine(d, static), config, scenarios, reference=ref)
        value = float(value)
        if k == 0:
            compile_time = time.perf_counter() - t
        tr.record(d, value, metrics)  # no early stopping: the budget is fixed
    return tr.finish(static, message, compile_time, stopped)


def local_search(schedule: AbstractDesign, config: TuningConfig, scenarios: ScenarioSet, *,
                 n_designs: int, sigma: float = 0.3, seed: int | None = None, tuned=None,
                 progress: bool = True, reference=None) -> TuningResult:
    """Gradient-free (1+1) evolution strategy: start at `schedule`; each evaluation
    perturbs the best point so far by `sigma` times a standard normal vector in the
    unconstrained variables, keeps it if it is better, and adapts `sigma` by the 1/5th
    success rule (x1.5 on success, x0.9 otherwise). `n_designs` evaluations, the first
    one `schedule` itself; draws from `PRNGKey(seed)` (default `config.seed`)."""
    _check_schedule(schedule)
    if n_designs < 1:
        raise ValueError(f"`local_search(n_designs=...)` must be >= 1; got {n_designs}.")
    if not sigma > 0:
        raise ValueError(f"`local_search(sigma=...)` must be > 0; got {sigma!r}.")
    spec = filter_spec(schedule, config.tuned if tuned is None else tuned)
    diff, static = eqx.partition(schedule, spec)
    flat, unravel = jax.flatten_util.ravel_pytree(diff)
    noise = jr.normal(jr.PRNGKey(config.seed if seed is None else seed),
                      (n_designs, flat.shape[0]), flat.dtype)
    ref = _reference(schedule, config, scenarios, reference)
    tr = _Tracker("local", n_designs, scenarios.n, config, progress, ref)
    z_best, f_best, compile_time = flat, np.inf, 0.0
    for k in range(n_designs):
        z = flat if k == 0 else z_best + sigma * noise[k]
        d = unravel(z)
        t = time.perf_counter()
        value, metrics = evaluate(eqx.combine(d, static), config, scenarios, reference=ref)
        value = float(value)
        if k == 0:
            compile_time = time.perf_counter() - t
        better = value < f_best and tr.admissible(metrics)
        if k > 0:
            sigma *= 1.5 if better else 0.9
        if better:
            z_best, f_best = z, value
        tr.record(d, value, metrics)
    return tr.finish(static, f"evaluated {n_designs} designs", compile_time, False)


OPTIMISER_FNS = {"adam": adam, "bfgs": bfgs, "lm": levenberg_marquardt}


def optimise(schedule: AbstractDesign, config: TuningConfig, scenarios: ScenarioSet, *,
             method: str | None = None, progress: bool = True, **kwargs) -> TuningResult:
    """Run the optimiser `method` (default `config.optimiser`: "adam", "bfgs", "lm")."""
    method = config.optimiser if method is None else method
    if method not in OPTIMISER_FNS:
        raise ValueError(f"unknown optimiser {method!r}; choose one of "
                         f"{', '.join(OPTIMISER_FNS)}.")
    return OPTIMISER_FNS[method](schedule, config, scenarios, progress=progress, **kwargs)
