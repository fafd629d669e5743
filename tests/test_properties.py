"""Property-based tests (hypothesis): frames, recordings, feasibility and equilibria.

Each property holds for every input hypothesis draws (few examples each, so that the
file runs in well under a minute; failures are shrunk to a minimal case)."""

import math

import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st

import pmsmjax as pj
from pmsmjax import analysis


SETTINGS = settings(max_examples=40, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])
finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
angles = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
DRIVE = pj.preset("zhang750")
SALIENT = pj.PMSMParams(R_s=0.78, L_d=1.0e-3, L_q=4.9e-3, psi_f=0.056, n_p=5.0)


# ----------------------------------------------------------------------------- frames

@SETTINGS
@given(x=st.tuples(finite, finite), theta=angles)
def test_park_round_trip_and_norm(x, theta):
    x = np.asarray(x)
    dq = np.asarray(pj.park(x, theta))
    np.testing.assert_allclose(np.asarray(pj.inv_park(dq, theta)), x, atol=1e-9 * (
        1 + np.abs(x).max()))
    np.testing.assert_allclose(np.linalg.norm(dq), np.linalg.norm(x), rtol=1e-12, atol=1e-12)
    # park at theta + 2 pi k is the same transform
    np.testing.assert_allclose(np.asarray(pj.park(x, theta + 2 * math.pi)), dq,
                               atol=1e-9 * (1 + np.abs(x).max()))


@SETTINGS
@given(x=st.tuples(finite, finite, finite))
def test_clarke_round_trip_keeps_the_zero_sequence(x):
    x = np.asarray(x)
    ab, z = pj.clarke(x), pj.clarke0(x)
    np.testing.assert_allclose(np.asarray(pj.inv_clarke(ab, z)), x,
                               atol=1e-12 * (1 + np.abs(x).max()))


@SETTINGS
@given(x=st.lists(finite, min_size=6, max_size=6))
def test_vsd_round_trip(x):
    x = np.asarray(x)
    ab, xy, o = pj.vsd(x)
    np.testing.assert_allclose(np.asarray(pj.inv_vsd(ab, xy, o)), x,
                               atol=1e-10 * (1 + np.abs(x).max()))


@SETTINGS
@given(theta=angles, k=st.integers(-50, 50))
def test_wrap_angle_interval_and_periodicity(theta, k):
    w = float(pj.wrap_angle(theta))
    assert -math.pi < w <= math.pi
    assert abs(math.remainder(theta - w, 2 * math.pi)) < 1e-9
    w2 = float(pj.wrap_angle(theta + 2 * math.pi * k))
    d = abs(w - w2)
    assert min(d, 2 * math.pi - d) < 1e-8


# ----------------------------------------------------------------------------- recordings

@SETTINGS
@given(n=st.integers(2, 60), T_s=st.floats(1e-5, 1e-2), t0=st.floats(-10.0, 10.0),
       seed=st.integers(0, 2 ** 31 - 1), ext=st.sampled_from([".npz", ".csv"]),
       extra=st.booleans())
def test_recording_round_trip(tmp_path_factory, n, T_s, t0, seed, ext, extra):
    rng = np.random.default_rng(seed)
    arrays = dict(t=t0 + T_s * np.arange(n), u_ab=rng.normal(size=(n, 2)) * 300,
                  i_ab=rng.normal(size=(n, 2)) * 10)
    if extra:
        arrays.update(theta=rng.uniform(-math.pi, math.pi, n), w_m=rng.normal(size=n),
                      tau_L=rng.normal(size=n))
    path = tmp_path_factory.mktemp("rec") / f"r{ext}"
    pj.save_recording(path, pj.RecordedData(**arrays))
    back = pj.load_recording(path)
    assert set(back.names) == set(arrays)
    for k, v in arrays.items():
        np.testing.assert_array_equal(getattr(back, k), v)  # exact: 17 digits in CSV


# ----------------------------------------------------------------------------- analysis

design = st.tuples(
    st.floats(-1.5, 1.5).filter(lambda w: abs(w) > 1e-3),  # speed (p.u.)
    st.floats(-2.0, 2.0), st.floats(-2.0, 2.0),  # i_d, i_q (p.u.)
    st.floats(0.0, 5.0), st.floats(0.0, 2.0))  # zeta1, ratio


@settings(max_examples=25, deadline=None)
# eight designs in every example: one compiled program per dtype (a batch of 1 to 8
# compiled one per size and dtype, 17 s against 3 s; the property is per design)
@given(points=st.lists(design, min_size=8, max_size=8))
def test_classify_status_is_always_defined_and_float32_agrees(points):
    p = np.asarray(points)
    w0 = p[:, 0] * DRIVE.w_rated
    i0 = p[:, 1:3] * DRIVE.base.I_b
    c64 = analysis.classify_designs(SALIENT, w0, i0, p[:, 3], p[:, 4])
    st64 = np.asarray(c64.status)
    assert np.all(np.isin(st64, [-1, 0, 1, 2]))
    # where a design is degenerate (ratio or zeta1 0 makes G1 singular) it says so;
    # otherwise the designed equilibrium's angle is finite
    ok = st64 >= 0
    assert np.all(np.isfinite(np.asarray(c64.principal_theta)[ok]))
    assert not np.any(np.isnan(np.asarray(c64.principal_theta)[ok]))
    c32 = analysis.classify_designs(SALIENT, w0, i0, p[:, 3], p[:, 4], dtype=jnp.float32)
    st32 = np.asarray(c32.status)
    assert np.all(np.isin(st32, [-1, 0, 1, 2]))
    # float32 may flip a status only next to a boundary (a near-double root or a zero
    # ratio): where both are feasible/infeasible the angles agree
    both = (st64 >= 0) & (st64 == st32)
    np.testing.assert_allclose(np.asarray(c32.principal_theta)[both],
                               np.asarray(c64.principal_theta)[both], atol=2e-3)


@settings(max_examples=15, deadline=None)
@given(w=st.floats(-1.5, 1.5), i_q=st.floats(-2.0, 2.0),
       k_L=st.floats(0.5, 1.5), k_psi=st.floats(0.8, 1.2))
def test_generic_equilibria_never_leak_nan(w, i_q, k_L, k_psi):
    obs = pj.observers.make_observer("leso", DRIVE).with_motor(
        pj.PMSMParams(R_s=DRIVE.motor.R_s, L_d=k_L * DRIVE.motor.L_d,
                      L_q=k_L * DRIVE.motor.L_q, psi_f=k_psi * DRIVE.motor.psi_f,
                      n_p=DRIVE.motor.n_p))
    eq = analysis.equilibria(obs, DRIVE.motor, w * DRIVE.w_rated,
                             jnp.array([0.0, i_q]) * DRIVE.base.I_b, method="generic")
    status = int(eq.status)
    assert status in (-1, 0, 2)
    v = np.asarray(eq.valid)
    if status == 0:
        assert v.any()
        assert np.all(np.isfinite(np.asarray(eq.theta)[v]))
        assert np.all(np.isfinite(np.asarray(eq.x)[v]))
        assert np.all(np.isfinite(np.asarray(eq.jacobian)[v]))
    else:
        assert not v.any()
    assert not np.any(np.isnan(np.asarray(eq.theta)[v]))
