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


@pytest.mark.parametrize("T_s, save_every, t_end", [(125e-6, 4, 0.3), (1 / 6600, 4, 0.15),
                                                    (250e-6, 2, 0.1), (62.5e-6, 1, 0.0301)])
def test_static_window_is_a_time(T_s, save_every, t_end):
    """The static window holds the saved samples at t >= 0.8 t_end (the samples as
    `simulate` saves them: the first of every `save_every` steps), whatever the sampling
    period and `save_every`; counted here in integers of steps, a route without the time
    arithmetic."""
    n_steps = round(t_end / T_s) // save_every * save_every
    k = np.arange(0, n_steps, save_every)  # the saved steps
    t = k * T_s
    got = np.asarray(pj.static_window(jnp.asarray(t)))
    want = 5 * k >= 4 * n_steps  # k T_s >= 0.8 N T_s
    np.testing.assert_array_equal(got, want)
    assert pj.STATIC_WINDOW == 0.2
    # batched times: the same window per row
    both = np.asarray(pj.static_window(jnp.stack([jnp.asarray(t), jnp.asarray(t) + 1.0])))
    np.testing.assert_array_equal(both, np.stack([want, want]))


def test_settling_time_from_a_start():
    """`t_from`: the samples before it are ignored, the time counts from it; a loop over
    the samples as the reference."""
    t = np.arange(100) * 0.01
    err = np.where((t > 0.2) & (t < 0.55), 3.0, 0.5)
    err[:10] = 9.0  # outside the band, but before the start
    for t_from in (0.15, 0.3, 0.6):
        outside = [j for j in range(100) if t[j] >= t_from - 1e-9 and abs(err[j]) > 1.0]
        want = t[outside[-1] + 1] - t_from if outside else 0.0
        got = float(pj.settling_time(t, err, 1.0, t_from=t_from))
        assert got == pytest.approx(want, abs=1e-12), t_from
    assert float(pj.settling_time(t, err, 1.0)) == pytest.approx(0.55, abs=1e-12)
    # batched: one start per run
    two = pj.settling_time(t, np.stack([err, err]), 1.0, t_from=jnp.array([0.15, 0.6]))
    np.testing.assert_allclose(np.asarray(two), [0.4, 0.0], atol=1e-12)


def test_run_metrics_against_numpy():
    """`pmsmjax.run_metrics`, the one definition of the per-run metrics, recomputed in
    NumPy on synthetic runs: a decaying error with noise, one with a non-finite sample
    (180 deg, not ok, lost lock), one that diverged."""
    from .helpers import lock_status_loop

    rng = np.random.default_rng(1)
    n, dt = 500, 4e-4  # 0.2 s
    t = np.arange(n) * dt
    th = np.stack([0.5 * np.exp(-t / 0.02) + 0.03 + 0.002 * rng.standard_normal(n)] * 3)
    th[1, 300] = np.nan
    w_err = 2.0 * rng.standard_normal((3, n))
    ok = np.array([True, True, False])
    traj = types.SimpleNamespace(t=jnp.asarray(np.broadcast_to(t, th.shape)),
                                 theta_err=jnp.asarray(th), w_m=jnp.asarray(w_err),
                                 w_hat=jnp.zeros((3, n)), ok=jnp.asarray(ok))
    m = {k: np.asarray(v) for k, v in pj.run_metrics(
        traj, lock_deg=30.0, settle_from=0.01, settle_band_deg=1.0).items()}
    win = t >= 0.8 * n * dt - 1e-9
    for j in range(3):
        d = np.degrees(np.where(np.isfinite(th[j]), th[j], np.pi))
        assert m["static_deg"][j] == pytest.approx(d[win].mean(), rel=1e-12)
        assert m["noise_rad_s"][j] == pytest.approx(w_err[j][win].std(), rel=1e-9)
        assert m["rms_deg"][j] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-9)
        assert m["max_abs_deg"][j] == pytest.approx(np.max(np.abs(d)), rel=1e-12)
        out = np.nonzero((t >= 0.01 - 1e-9) & (np.abs(d - d[win].mean()) > 1.0))[0]
        settle = t[out[-1] + 1] - 0.01 if out.size else 0.0
        assert m["settle_s"][j] == pytest.approx(settle, abs=1e-12)
        ref = lock_status_loop(t, th[j], ok=bool(ok[j]), lock_deg=30.0, start_locked=True)
        assert bool(m["lost_lock"][j]) == ref[2]
        if ref[2]:  # when: the plain loop's time of the loss
            assert m["t_lost"][j] == pytest.approx(ref[3], abs=1e-12)
        else:
            assert np.isnan(m["t_lost"][j])
        assert bool(m["ok"][j]) == (j == 0)
    assert not m["lost_lock"][0] and m["lost_lock"][1] and m["lost_lock"][2]
    # the runs start with the observer on the true angle: one that slips at once and only
    # settles back after 80 ms lost lock, though judged as an acquisition it was not
    slip = np.where(t < 0.08, 1.0, 0.0)
    one = types.SimpleNamespace(t=jnp.asarray(t), theta_err=jnp.asarray(slip),
                                w_m=jnp.zeros(n), w_hat=jnp.zeros(n), ok=jnp.asarray(True))
    assert bool(pj.run_metrics(one, lock_deg=30.0)["lost_lock"])
    assert lock_status_loop(t, slip, lock_deg=30.0, start_locked=True)[2]
    assert not lock_status_loop(t, slip, lock_deg=30.0)[2]
    th_deg, w, ok_ = pj.run_errors(traj)
    assert float(th_deg[1, 300]) == 180.0 and bool(ok_[0]) and not bool(ok_[1])
    # differentiable: the static error's gradient wrt an offset of the error is 1
    g = jax.grad(lambda c: pj.run_metrics(types.SimpleNamespace(
        **{**vars(traj), "theta_err": traj.theta_err + c}))["static_deg"][0])(0.0)
    assert float(g) == pytest.approx(180.0 / math.pi, rel=1e-12)
