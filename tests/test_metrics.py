"""The metrics module (`pmsmjax._sim._metrics`): reporting statistics and the differentiable
trajectory metrics of the tuner."""

import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj


def test_error_stats_numbers():
    s = pj.error_stats([1.0, -3.0, 2.0])
    assert s["mean"] == 0.0
    assert s["max_abs"] == 3.0
    assert s["rms"] == pytest.approx(math.sqrt(14.0 / 3.0), rel=1e-15)
    assert s["std"] == pytest.approx(math.sqrt(14.0 / 3.0), rel=1e-15)
    with pytest.raises(ValueError, match="at least one sample"):
        pj.error_stats([])


def test_settled_mask_waits_after_every_reference_step():
    t = np.arange(10) * 0.1  # s
    w_ref = np.r_[np.zeros(3), np.ones(7)]  # step at t = 0.3 s
    tau = np.r_[np.zeros(6), np.ones(4)]  # step at t = 0.6 s
    mask = pj.settled_mask(t, w_ref, tau, t_settle=0.2)
    want = np.array([0, 0, 1, 0, 0, 1, 0, 0, 1, 1], bool)
    np.testing.assert_array_equal(mask, want)
    np.testing.assert_array_equal(pj.settled_mask(t, t_settle=0.35), t >= 0.35)


def test_trajectory_metrics_exponential_decay():
    """For theta_err = theta0 exp(-t / tau) sampled every dt the settling surrogate is
    sqrt(4 dt^2 sum_k k q^k) with q = exp(-2 dt / tau), i.e. dt / sinh(dt / tau) in
    closed form (tau to O((dt/tau)^2)); the static error and speed noise are ~0; the
    metrics are differentiable, with the closed form's derivative."""
    T_s, save_every, tau, theta0 = 1e-4, 2, 0.01, math.radians(30.0)
    t = jnp.arange(5000) * T_s * save_every  # 1 s
    traj = types.SimpleNamespace(t=t, theta_err=theta0 * jnp.exp(-t / tau),
                                 w_m=jnp.ones_like(t), w_hat=jnp.ones_like(t), ok=True)
    m = pj.trajectory_metrics(traj, t_transient=0.5, T_s=T_s, save_every=save_every,
                              theta_err0=theta0)
    dt = T_s * save_every
    # the record's truncation (exp(-2 t_end / tau) = e^-200) and the static error's
    # mean (e^-50) are negligible; the square root's 1e-12 floor is 5e-9 relative here
    assert float(m["settle_s"]) == pytest.approx(dt / math.sinh(dt / tau), rel=2e-8)
    assert float(m["settle_s"]) == pytest.approx(tau, rel=(dt / tau) ** 2)
    assert abs(float(m["theta_ss_deg"])) < 1e-12
    assert float(m["noise_rad_s"]) == pytest.approx(1e-6)  # sqrt of the 1e-12 floor
    assert bool(m["ok"])

    def settle(k):
        tr = types.SimpleNamespace(**{**vars(traj), "theta_err": theta0 * jnp.exp(-k * t)})
        return pj.trajectory_metrics(tr, t_transient=0.5, T_s=T_s, save_every=save_every,
                                     theta_err0=theta0)["settle_s"]

    # d/dk of dt / sinh(dt k) at k = 1/tau (~ -tau^2), to the same 1e-8
    g = jax.grad(settle)(1.0 / tau)
    x = dt / tau
    assert float(g) == pytest.approx(-dt ** 2 * math.cosh(x) / math.sinh(x) ** 2, rel=2e-8)
