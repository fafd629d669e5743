r"""Simulate a design on a scenario set and score it: the step between the scenario sets
and the searches.

An `Evaluator` holds one scenario set and the reference metrics (the paper design's on
the same runs) and offers, compiled once each:

- `metrics(x)`: the `Metrics` of physical design `x` on every run;
- `metrics_many(xs)`: the same for a batch of designs (vmapped: a CMA-ES generation is
  one batch of `population x runs` closed-loop simulations);
- `value(z)`, `values(zs)`, `value_and_grad(z)`: the objective $J$ of unconstrained
  designs (`tuning.objective.objective`), and its gradient by reverse-mode
  differentiation through the closed-loop simulations.

`cost` is the number of closed-loop simulations one evaluation of one design runs (the
set's size), the currency of the searches' equal budgets.
"""

from __future__ import annotations

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


class Evaluator:
    """Scores designs on the scenario set `sset` (see the module docstring)."""

    def __init__(self, problem: TuningProblem, space: DesignSpace, sset: ScenarioSet,
                 *, w_noise: float | None = None):
        self.problem = problem if w_noise is None else problem.replace(w_noise=w_noise)
        self.space = space
        self.sset = sset
        self.cost = sset.n
        problem = self.problem
        drive, foc = problem.drive(), problem.controller()

        def metrics(x=None):
            traj = simulate_set(lambda motor: space.observer(x, motor), drive, foc, sset,
                                T_s=problem.T_s, noise_std=problem.noise_std,
                                save_every=problem.save_every)
            return run_metrics(traj, problem)

        self._metrics = metrics
        self.metrics = jax.jit(metrics)
        self.metrics_many = jax.jit(jax.vmap(metrics))
        #: the paper's design as published on the same runs
        self.reference: Metrics = jax.jit(lambda: metrics(None))()

        def value(z, ref):
            return objective(metrics(space.to_physical(z)), ref, problem)[0]

        self._value_and_grad = jax.jit(jax.value_and_grad(value))
        self._values = jax.jit(jax.vmap(value, in_axes=(0, None)))
        w_base = problem.w_noise

        def reweighed_value(z, ref, w_new):
            m = reweigh(metrics(space.to_physical(z)), problem, w_base, w_new)
            return objective(m, ref, problem)[0]

        # one program for every other noise weight (the front designs): the weight is
        # an argument, not a constant compiled in
        self._reweighed_value_and_grad = jax.jit(jax.value_and_grad(reweighed_value))
        self._reweighed_values = jax.jit(jax.vmap(reweighed_value, in_axes=(0, None, None)))

    def perturbed_reference(self, eps: float) -> Metrics:
        """The metrics of the paper's design with every tunable design parameter of the
        observer contract (`tunable`) multiplied by `1 + eps` (its own parametrisation:
        zhang2022's schedule (38) stays)."""
        from pmsmjax.observers import make_observer, observer_class

        problem, space = self.problem, self.space
        drive, foc = problem.drive(), problem.controller()
        vals = {k: space.paper_design[k] * (1.0 + eps)
                for k in observer_class(problem.observer).tunable}

        def build(motor):
            return make_observer(problem.observer, drive, motor=motor).with_design(**vals)

        traj = jax.jit(lambda: simulate_set(build, drive, foc, self.sset, T_s=problem.T_s,
                                            noise_std=problem.noise_std,
                                            save_every=problem.save_every))()
        return run_metrics(traj, problem)

    def with_noise_weight(self, w_noise: float) -> Evaluator:
        """The same runs and reference, scored with another noise weight (a point of the
        tracking-versus-noise front). Every such evaluator of one `Evaluator` runs the
        same compiled programs, with the weight as their argument."""
        ev = Evaluator.__new__(Evaluator)
        ev.__dict__.update(self.__dict__)
        problem = self.problem.replace(w_noise=w_noise)
        ev.problem = problem
        ev.reference = reweigh(self.reference, problem, self.problem.w_noise, w_noise)
        w = jnp.asarray(w_noise, jnp.result_type(float))
        vg, vs = self._reweighed_value_and_grad, self._reweighed_values
        ev._value_and_grad = lambda z, ref: vg(z, ref, w)
        ev._values = lambda zs, ref: vs(zs, ref, w)
        return ev

    def value_and_grad(self, z):
        return self._value_and_grad(z, self.reference)

    def value(self, z):
        return self._values(jnp.asarray(z)[None], self.reference)[0]

    def values(self, zs):
        return self._values(jnp.asarray(zs), self.reference)


__all__ = ["Evaluator"]
