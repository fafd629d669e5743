r"""Simulate a design on a scenario set and score it: the step between the scenario sets
and the searches.

An `Evaluator` holds one scenario set and the reference metrics (the paper design's on
the same runs) and offers:

- `metrics(x)`: the `Metrics` of physical design `x` on every run;
- `metrics_many(xs)`: the same for a batch of designs (vmapped: a CMA-ES generation is
  one batch of `population x runs` closed-loop simulations);
- `value(z)`, `values(zs)`, `value_and_grad(z)`: the objective $J$ of unconstrained
  designs (`tuning.objective.objective`), and its gradient by reverse-mode
  differentiation through the closed-loop simulations.

`cost` is the number of closed-loop simulations one evaluation of one design runs (the
set's size), the currency of the searches' equal budgets.

**Compiled programs.** Every evaluator of one problem and design space runs the same
compiled programs, with the scenario set, the reference and the noise weight as their
arguments: one program per shape (number of runs, run length, batch of designs), not one
per set. On the main job's quick problem this takes a third off the compile work of a
whole tuning run (BENCHMARKS.md, "Closed-loop tuning").
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from .design_space import DesignSpace
from .objective import Metrics, objective, run_metrics
from .problem import TuningProblem
from .scenarios import ScenarioSet, simulate_set


def reweigh(m: Metrics, problem: TuningProblem, w_old: float, w_new: float) -> Metrics:
    """`m` with its runs' losses carrying the noise weight `w_new` instead of `w_old`
    (runs that diverged keep their loss)."""
    d = (w_new - w_old) * m.noise_rad_s / problem.noise_unit_rad_s
    return eqx.tree_at(lambda t: t.loss, m, jnp.where(m.ok, m.loss + d, m.loss))


class _Programs:
    """The compiled programs of one (problem, design space), shared by every `Evaluator`
    of it: the scenario set is an argument of each program, not a constant compiled in,
    so sets of the same size and run length (the training and held-out sets, a notebook's
    single runs) run the same programs, and each program compiles once per shape."""

    def __init__(self, problem: TuningProblem, space: DesignSpace):
        drive, foc = problem.drive(), problem.controller()
        w_base = problem.w_noise

        def score(build, sset):
            # every run of `sset` with the observer `build(motor)` builds, and its metrics
            traj = simulate_set(build, drive, foc, sset, T_s=problem.T_s,
                                noise_std=problem.noise_std, save_every=problem.save_every,
                                speed_from_angle=problem.speed_from_angle)
            return run_metrics(traj, problem)

        def metrics(x, sset):
            return score(lambda motor: space.observer(x, motor), sset)

        def perturbed(eps, sset):
            from pmsmjax.observers import make_observer, observer_class

            vals = {k: space.paper_design[k] * (1.0 + eps)
                    for k in observer_class(problem.observer).tunable}
            return score(lambda motor: make_observer(problem.observer, drive, motor=motor)
                         .with_design(**vals), sset)

        def value(z, ref, w_new, sset):
            # the objective with the runs' noise weight `w_new` (the problem's own weight
            # reproduces it exactly: `reweigh` adds zero); one program for every weight
            m = reweigh(metrics(space.to_physical(z), sset), problem, w_base, w_new)
            return objective(m, ref, problem)[0]

        self.metrics = jax.jit(metrics)
        self.metrics_many = jax.jit(jax.vmap(metrics, in_axes=(0, None)))
        self.perturbed = jax.jit(perturbed)
        self.value_and_grad = jax.jit(jax.value_and_grad(value))
        self.values = jax.jit(jax.vmap(value, in_axes=(0, None, None, None)))


@functools.lru_cache(maxsize=8)
def _programs(problem: TuningProblem, space: DesignSpace) -> _Programs:
    return _Programs(problem, space)


class Evaluator:
    """Scores designs on the scenario set `sset` (see the module docstring). Evaluators of
    one problem and design space share their compiled programs (the set is an argument)."""

    def __init__(self, problem: TuningProblem, space: DesignSpace, sset: ScenarioSet,
                 *, w_noise: float | None = None):
        self.problem = problem if w_noise is None else problem.replace(w_noise=w_noise)
        self.space = space
        self.sset = sset
        self.cost = sset.n
        self.programs = _programs(self.problem, space)
        #: the paper's design as published on the same runs
        self.reference: Metrics = self.programs.metrics(None, sset)
        self._w = jnp.asarray(self.problem.w_noise, jnp.result_type(float))

    def metrics(self, x) -> Metrics:
        """The `Metrics` of physical design `x` on every run."""
        return self.programs.metrics(x, self.sset)

    def metrics_many(self, xs) -> Metrics:
        """The `Metrics` of a batch of physical designs `xs` (leading axis)."""
        return self.programs.metrics_many(xs, self.sset)

    def perturbed_reference(self, eps: float) -> Metrics:
        """The metrics of the paper's design with every tunable design parameter of the
        observer contract (`tunable`) multiplied by `1 + eps` (its own parametrisation:
        zhang2022's schedule (38) stays)."""
        return self.programs.perturbed(jnp.asarray(eps, jnp.result_type(float)), self.sset)

    def with_noise_weight(self, w_noise: float) -> Evaluator:
        """The same runs and reference, scored with another noise weight (a point of the
        tracking-versus-noise front). Every such evaluator of one `Evaluator` runs the
        same compiled programs, with the weight as their argument."""
        ev = Evaluator.__new__(Evaluator)
        ev.__dict__.update(self.__dict__)
        problem = self.problem.replace(w_noise=w_noise)
        ev.problem = problem
        ev.reference = reweigh(self.reference, problem, self.problem.w_noise, w_noise)
        ev._w = jnp.asarray(w_noise, jnp.result_type(float))
        return ev

    def value_and_grad(self, z):
        return self.programs.value_and_grad(z, self.reference, self._w, self.sset)

    def value(self, z):
        # a batch of one (its own program): through the gradient's program it saves that
        # compile but costs a backward pass per call, about 3x the run time of the local
        # search, which on the main job's full problem outweighs the compile
        return self.values(jnp.asarray(z)[None])[0]

    def values(self, zs):
        return self.programs.values(jnp.asarray(zs), self.reference, self._w, self.sset)


__all__ = ["Evaluator"]
