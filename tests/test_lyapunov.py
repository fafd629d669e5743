"""Lyapunov equation (48) and the slowly-varying certificate of zhang2022 §V."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import ESODesign, eso_gains, psi_a


DRIVE = pj.preset("zhang750")
DESIGN = ESODesign.zhang38(DRIVE.w_rated)
# Reduced resolution: the defaults are finer, the relations tested are the same.
FAST = dict(n_speed=21, n_dirs=256, alphas=(0.8, 0.99), n_time=80, n_k1_speeds=5,
            radii=np.geomspace(1e-6, 1.0, 40))


@pytest.fixture(scope="module")
def cert():
    return analysis.slowly_varying_certificate(DRIVE, DESIGN, (0.3, 1.0), **FAST)


def _A(w0, i0=(0.0, 0.0)):
    i0 = jnp.asarray(i0)
    z1, w1 = 1.5 + w0 / DRIVE.w_rated, None
    w1 = 1.5 * w0 / z1
    g = eso_gains(psi_a(DRIVE.motor, i0), w0, z1, w1, 1.0, 2 * math.pi * 50)
    return analysis.eso_linearization(w0, i0, g, DRIVE.motor)


def test_lyapunov_solve_matches_scipy_and_is_positive_definite():
    for w in (0.05, 0.3, 1.0):
        A = _A(w * DRIVE.w_rated, (0.2, 0.9))
        D = jnp.diag(jnp.array([10.0, 10.0, 1.0, 1e-3]))  # scale as in the certificate
        A = D @ A @ jnp.linalg.inv(D)
        P = analysis.lyapunov_solve(A)
        res = P @ A + A.T @ P + jnp.eye(4)
        assert float(jnp.max(jnp.abs(res))) < 1e-12 * float(jnp.linalg.norm(P) *
                                                             jnp.linalg.norm(A))
        ref = scipy.linalg.solve_continuous_lyapunov(np.asarray(A).T, -np.eye(4))
        np.testing.assert_allclose(P, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(P, P.T, atol=0)
        assert float(jnp.min(jnp.linalg.eigvalsh(P))) > 0


def test_lyapunov_derivative_matches_finite_differences():
    def P(w):
        return analysis.lyapunov_solve(_A(w))

    w, h = 0.4 * DRIVE.w_rated, 1e-3
    dP = jax.jacfwd(P)(w)
    fd = (P(w + h) - P(w - h)) / (2 * h)
    np.testing.assert_allclose(dP, fd, rtol=1e-5, atol=1e-9 * float(jnp.abs(dP).max()))


def test_certificate_constants_are_consistent(cert):
    c = jax.tree_util.tree_map(np.asarray, cert)
    assert int(c.status) == 0
    assert c.lyap_residual < 1e-10 and c.min_eig_P > 0
    assert c.sigma > 0 and 0 < c.gamma < c.sigma and c.k >= 1.0
    # paper constants bracket the sharp ones (c1 = 1/(2 rho) <= lambda_min(P), etc.)
    assert c.c1 <= c.c1_sharp <= c.c2_sharp <= c.c2
    np.testing.assert_allclose(c.c4, 2 * c.c2)
    np.testing.assert_allclose(c.c4_sharp, 2 * c.c2_sharp)
    assert c.c5 >= c.c5_sharp > 0
    np.testing.assert_allclose(c.c5, c.c5_paper * c.b)  # (63) with the true ||dA/dw||
    assert abs(c.b - 1.0) > 0.1  # (49)'s "= 1" does not hold
    # (59): c3 = 1 - 2 c2 k1 r >= the target at the chosen radius
    assert 1 - 2 * c.c2 * c.k1 * c.r >= c.c3 - 1e-12
    assert 1 - 2 * c.c2_sharp * c.k1_sharp * c.r_sharp >= c.c3_sharp - 1e-12
    np.testing.assert_allclose(c.eps, c.c3 / c.c5)
    np.testing.assert_allclose(c.eps_sharp, c.c3_sharp / c.c5_sharp)
    assert 0 < c.eps <= c.eps_sharp and c.eps < c.eps_sup
    assert 0 < c.r_init < c.r and 0 < c.r_init_sharp < c.r_sharp


def test_exponential_bound_holds(cert):
    """||exp(tA)|| <= k exp(-gamma t) at every speed of the grid and many t."""
    k, gam = float(cert.k), float(cert.gamma)
    d = jnp.array([1 / DRIVE.base.psi_b, 1 / DRIVE.base.psi_b, 1.0, 1 / DRIVE.base.w_b])
    t = np.concatenate([[0.0], np.geomspace(1e-6, 30 / gam, 120)])
    for w in np.asarray(cert.speeds)[::4]:
        A = np.asarray(d[:, None] * _A(w) / d[None, :])
        nrm = [np.linalg.norm(scipy.linalg.expm(tt * A), 2) for tt in t]
        assert np.all(np.array(nrm) <= k * np.exp(-gam * t) * (1 + 1e-6))


def test_k1_bounds_the_remainder(cert):
    """||g(z) - A z|| <= k1 ||z||^2 on random points of the ball of radius r."""
    from pmsmjax.analysis._lyapunov import _ScaledDynamics, _state_scale

    obs = pj.LESOObserver(DRIVE.three_phase_motor, DESIGN)
    dyn = _ScaledDynamics(observer=obs, plant=DRIVE.three_phase_motor, i0=jnp.zeros(2),
                          d=_state_scale(DRIVE, obs, "pu", jnp.float64), frame="observer")
    r, k1 = float(cert.r), float(cert.k1)
    z = np.random.default_rng(0).normal(size=(2000, 4))
    z = z / np.linalg.norm(z, axis=1, keepdims=True) * r * np.random.default_rng(1).uniform(
        0.1, 1.0, (2000, 1))
    for w in np.asarray(cert.speeds)[::5]:
        A = dyn.A(w)
        rem = jax.vmap(lambda zz: jnp.linalg.norm(dyn.g(zz, w) - A @ zz))(jnp.asarray(z))
        assert np.all(np.asarray(rem) <= k1 * np.sum(z ** 2, 1) * (1 + 1e-6))


def test_ramp_inside_the_bound_converges(cert):
    eps = float(cert.eps)
    # start on the certified ball (all of it in the angle), ramp across part of the range
    th0 = math.degrees(float(cert.r_init)) * 0.99
    run = analysis.simulate_ramp(DRIVE, DESIGN, (0.3, 0.32), 0.9 * eps, theta0_deg=th0,
                                 model="paper", tol_deg=1e-6)
    assert bool(run.converged) and int(run.status) == 0
    assert float(run.final_norm) < 1e-3 * float(cert.r_init)
    # and the true error dynamics (speed forcing, gains at w_hat) converge too
    run = analysis.simulate_ramp(DRIVE, DESIGN, (0.3, 0.32), 0.9 * eps, theta0_deg=th0,
                                 model="observer", tol_deg=1e-6)
    assert bool(run.converged)


def test_very_fast_ramp_fails_in_the_true_error_dynamics():
    run = analysis.simulate_ramp(DRIVE, DESIGN, (0.1, 1.0), 1e6, theta0_deg=10.0,
                                 model="observer")
    assert not bool(run.converged) and int(run.status) == 0


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="speed_range"):
        analysis.slowly_varying_certificate(DRIVE, DESIGN, (0.0, 1.0))
    with pytest.raises(ValueError, match="speed_range"):
        analysis.slowly_varying_certificate(DRIVE, DESIGN, (1.0, 0.5))
    with pytest.raises(ValueError, match="scale"):
        analysis.slowly_varying_certificate(DRIVE, DESIGN, scale="mixed")
    with pytest.raises(ValueError, match="design"):
        analysis.slowly_varying_certificate(DRIVE, None)
    with pytest.raises(ValueError, match="c3"):
        analysis.slowly_varying_certificate(DRIVE, DESIGN, c3=1.0)
    with pytest.raises(ValueError, match="rate"):
        analysis.simulate_ramp(DRIVE, DESIGN, (0.1, 0.2), 0.0)
    with pytest.raises(ValueError, match="model"):
        analysis.simulate_ramp(DRIVE, DESIGN, (0.1, 0.2), 1.0, model="plant")
