"""The closed-loop tuner's gradient for the parallel-model estimator (stumper_mt5, its
paper's drive at 16 kHz): the behaviour the removed slow test `test_quick_tuning_runs`
(a whole `python -m tuning --observer parallel-model --quick` job, about 8 minutes) was
the only one to exercise, on one short training run.

Checked against central differences of the same objective through the closed loop, at
the paper's design, in the tuner's unconstrained coordinates (tracking-filter bandwidth
and damping, derivative low pass T_LP). `test_tuning.py` does the same for the ESO only.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import tuning as tg


def test_closed_loop_gradient_matches_central_differences():
    p = tg.TuningProblem.quick(observer="parallel-model", n_train=1, n_heldout=1,
                               t_end=0.04, budget=12, population=4)
    assert p.motor == "stumper_mt5" and p.T_s == 62.5e-6  # its per-motor defaults
    space = tg.DesignSpace(p)
    assert [c.name for c in space.coordinates] == ["w_tf", "zeta_tf", "T_LP"]
    ev = tg.Evaluator(p, space, tg.training_set(p).take([0]))
    z = space.to_unconstrained(space.paper_point())
    v, g = ev.value_and_grad(z)
    g = np.asarray(g)
    assert np.isfinite(float(v)) and np.all(np.isfinite(g))
    # the value of value_and_grad is the objective's: two compiled programs, which may
    # order the same sums differently, so equal to rounding
    assert float(ev.value(z)) == pytest.approx(float(v), rel=1e-12)
    eps = 1e-4
    fd = np.zeros(space.n)
    for i in range(space.n):
        e = jnp.zeros(space.n).at[i].set(eps)
        fd[i] = (float(ev.value(z + e)) - float(ev.value(z - e))) / (2 * eps)
    # central differences: truncation eps^2/6 |f'''| ~ 1e-9 for O(1) derivatives in these
    # coordinates, rounding 1e-16/eps ~ 1e-12; the closed loop's soft constraints and
    # lock measures are smooth but steep, so allow 1e-4 of the gradient's size (per
    # component, as the T_LP component is 60 times smaller than the others)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.linalg.norm(fd))
    assert np.linalg.norm(fd) > 1e-2  # the design matters: the check is not vacuous
