"""`pmsmjax.lock_status`, the one definition of loss of lock, against a plain loop over
the samples, on constructed error sequences and on random ones."""

import math

import jax
import numpy as np
import pytest

import pmsmjax as pj

from .helpers import lock_status_loop


def _check(t, e, ok=True, **kw):
    got = {k: np.asarray(v) for k, v in pj.lock_status(t, e, ok=ok, **kw).items()}
    acq, t_acq, lost, t_lost = lock_status_loop(t, e, ok=ok, **kw)
    assert bool(got["acquired"]) == acq and bool(got["lost"]) == lost
    np.testing.assert_allclose(got["t_acquired"], t_acq, equal_nan=True)
    np.testing.assert_allclose(got["t_lost"], t_lost, equal_nan=True)
    return got


def test_constructed_cases():
    t = np.arange(1000) * 1e-3
    e = np.zeros(1000)
    assert not _check(t, e)["lost"]
    spike = e.copy()
    spike[100:105] = 1.5  # 5 ms at 86 deg: a transient (10 ms mean 43 deg), not a loss
    assert not _check(t, spike)["lost"]
    slip = e.copy()
    slip[500:520] = 1.2  # 20 ms
    g = _check(t, slip)
    assert g["lost"] and g["t_lost"] == pytest.approx(0.5, abs=5e-3)
    late = np.full(1000, 2.0)
    late[300:] = 0.1  # acquires at 0.3 s, never loses it: an unknown start is no loss
    g = _check(t, late)
    assert g["acquired"] and g["t_acquired"] == pytest.approx(0.3, abs=5e-3) and not g["lost"]
    overshoot = np.full(1000, 2.0)
    overshoot[150:170] = 0.3  # an acquisition passes through the band for 20 ms ...
    overshoot[200:] = 0.05  # ... and locks at 0.2 s: acquired there, no loss
    g = _check(t, overshoot)
    assert g["acquired"] and g["t_acquired"] == pytest.approx(0.2, abs=5e-3)
    assert not g["lost"]
    g = _check(t, overshoot, acquire_s=10e-3)  # without the hold it was a "loss"
    assert g["lost"] and g["t_acquired"] == pytest.approx(0.15, abs=5e-3)
    near_end = np.full(1000, 2.0)
    near_end[975:] = 0.0  # locks 25 ms before the end: held to the last whole window
    g = _check(t, near_end)
    assert g["acquired"] and g["t_acquired"] == pytest.approx(0.975, abs=5e-3)
    never = np.full(1000, 2.5)
    g = _check(t, never)
    assert not g["acquired"] and not g["lost"]
    # a run that starts in lock (the observer on the true angle): the same slips are losses
    g = _check(t, late, start_locked=True)  # out of lock from the first sample
    assert g["acquired"] and g["t_acquired"] == 0.0
    assert g["lost"] and g["t_lost"] == 0.0
    g = _check(t, never, start_locked=True)
    assert g["lost"] and g["t_lost"] == 0.0
    slips_at_once = np.zeros(1000)
    slips_at_once[12:340] = 2.0  # slips within 12 ms, back from 0.34 s (li, 0.1 p.u.)
    g = _check(t, slips_at_once)  # as an acquisition: acquired late, never lost
    assert not g["lost"] and g["t_acquired"] == pytest.approx(0.34, abs=5e-3)
    g = _check(t, slips_at_once, start_locked=True)
    # the first 10 ms window above 45 deg starts at 6 ms: 4 of its samples at 2 rad
    assert g["lost"] and g["t_lost"] == pytest.approx(0.006)
    nan = e.copy()
    nan[700] = np.nan
    g = _check(t, nan)
    assert g["lost"] and g["t_lost"] == pytest.approx(0.7)
    g = _check(t, e, ok=False)  # a diverged run lost lock
    assert g["lost"]
    for case in (e, spike, slip, nan):  # where the run starts in lock, the same verdicts
        a, b = _check(t, case), _check(t, case, start_locked=True)
        assert bool(a["lost"]) == bool(b["lost"])
        np.testing.assert_allclose(a["t_lost"], b["t_lost"], equal_nan=True)
    wrapped = e + 2 * math.pi  # the error is wrapped first
    assert not _check(t, wrapped)["lost"]
    spin = np.zeros(1000)
    spin[600:] = np.linspace(0, 40 * 2 * math.pi, 400)  # the estimate spins: some of its
    g = _check(t, spin)  # samples pass near the true angle, none stays: out of lock
    assert g["lost"] and g["t_lost"] == pytest.approx(0.6, abs=5e-3)


def test_random_sequences_and_batches():
    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.5e-3
    es = []
    for _ in range(40):
        e = np.zeros(400)
        for _ in range(rng.integers(0, 4)):
            a = rng.integers(0, 400)
            e[a:a + rng.integers(1, 60)] = rng.choice([-1, 1]) * rng.uniform(0.5, 3.0)
        es.append(e)
        _check(t, e, dwell_s=5e-3)
        _check(t, e, dwell_s=5e-3, acquire_s=20e-3)
        _check(t, e, dwell_s=5e-3, start_locked=True)
    es = np.stack(es)
    batch = jax.jit(lambda t, e: pj.lock_status(t, e, dwell_s=5e-3))(
        np.broadcast_to(t, es.shape), es)
    for j in range(es.shape[0]):
        ref = lock_status_loop(t, es[j], dwell_s=5e-3)
        assert bool(batch["lost"][j]) == ref[2]
