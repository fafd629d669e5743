"""Equilibria of the zhang2022 ESO error dynamics: quartic route (34)-(36) vs the general
route, residuals, stability by Routh-Hurwitz vs eigenvalues."""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import error_matrix, eso_gains, psi_a


DRIVE = pj.preset("zhang750")
M = DRIVE.motor
W2 = 2 * math.pi * 50
# A strongly salient machine (L_q / L_d = 4.9) where three nonzero equilibria and stable
# ones exist; Table I alone has a single, always unstable, nonzero equilibrium.
SALIENT = pj.PMSMParams(R_s=0.78, L_d=1.0e-3, L_q=4.9e-3, psi_f=0.056, n_p=5.0)


def _arr(motor):
    """Parameters as arrays, so that jitted functions do not recompile per machine."""
    return jax.tree_util.tree_map(jnp.asarray, motor)


def _random_designs(n, seed):
    rng = np.random.default_rng(seed)
    w0 = rng.choice([-1.0, 1.0], n) * rng.uniform(0.02, 1.5, n) * DRIVE.w_rated
    i0 = rng.uniform(-2.0, 2.0, (n, 2)) * DRIVE.base.I_b
    z1 = rng.uniform(0.05, 5.0, n)
    ratio = rng.uniform(0.05, 2.0, n)
    return w0, i0, z1, ratio


def _gains(motor, w0, i0, z1, ratio, zeta2=1.0, w2=W2):
    return eso_gains(psi_a(motor, i0), w0, z1, ratio * jnp.abs(w0), zeta2, w2)


@eqx.filter_jit
def _both(motor, w0, i0, z1, ratio, frame):
    def one(w0, i0, z1, ratio):
        g = _gains(motor, w0, i0, z1, ratio)
        return (analysis.quartic_equilibria(w0, i0, g, motor, frame=frame),
                analysis.eso_equilibria(w0, i0, g, motor, frame=frame, n_grid=128))
    return jax.vmap(one)(w0, i0, z1, ratio)


@jax.jit  # one program for both machines (their parameters are its inputs)
def _rhs_at_roots(motor, x, w0, i0, z1, ratio):
    return jax.vmap(jax.vmap(
        lambda x, w0, i0, z1, ratio: analysis.eso_rhs(
            x, w0, i0, _gains(motor, w0, i0, z1, ratio), motor),
        (0, None, None, None, None)), (0, 0, 0, 0, 0))(x, w0, i0, z1, ratio)


def _fd_max_real_eigenvalue(motor, w0, i0, z1, ratio, x):
    """Largest real part of the eigenvalues of the central-difference Jacobian of
    `eso_rhs` at each equilibrium `x` (n, 4 roots, 4), NaN where x is NaN."""
    x = np.nan_to_num(x)
    step = np.array([1e-7, 1e-7, 1e-7, 1e-3])  # V s, V s, rad, rad/s
    cols = []
    for k in range(4):
        e = np.zeros(4)
        e[k] = step[k]
        fp = np.asarray(_rhs_at_roots(_arr(motor), x + e, w0, i0, z1, ratio))
        fm = np.asarray(_rhs_at_roots(_arr(motor), x - e, w0, i0, z1, ratio))
        cols.append((fp - fm) / (2 * step[k]))
    J = np.stack(cols, -1)
    return np.linalg.eigvals(J).real.max(-1)


@pytest.mark.parametrize("motor", [M, SALIENT], ids=["tableI", "salient"])
def test_quartic_and_general_route_agree(motor):
    w0, i0, z1, ratio = _random_designs(200, seed=1)
    q, g = _both(_arr(motor), w0, i0, z1, ratio, "observer")
    assert np.all(np.asarray(q.status) == 0) and np.all(np.asarray(g.status) == 0)
    np.testing.assert_array_equal(np.asarray(q.n), np.asarray(g.n))
    tq = np.sort(np.nan_to_num(np.asarray(q.theta), nan=99.0), -1)
    tg = np.sort(np.nan_to_num(np.asarray(g.theta), nan=99.0), -1)[:, :4]
    np.testing.assert_allclose(tq, tg, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(q.stable), np.asarray(g.stable)[:, :4])
    # Both flags come from the same Routh-Hurwitz code: check them against eigenvalues of
    # a central-difference Jacobian of the error dynamics (NumPy), independent of both.
    ev = _fd_max_real_eigenvalue(motor, w0, i0, z1, ratio, np.asarray(q.x))
    v = np.asarray(q.valid)
    clear = v & (np.abs(ev) > 1e-6 * np.abs(w0)[:, None])
    assert clear.sum() > 0.9 * v.sum()
    np.testing.assert_array_equal(np.asarray(q.stable)[clear], ev[clear] < 0)
    # the paper's "either 1 or 3" nonzero equilibria (the cubic after t = 0 is divided out)
    assert set(np.unique(np.asarray(q.n_nonzero))) <= {1, 3}
    if motor is SALIENT:  # the test must exercise both cases and stable nonzero ones
        assert set(np.unique(np.asarray(q.n_nonzero))) == {1, 3}
        assert np.any(np.asarray(q.nonprincipal & q.stable))


@jax.jit
def _printed_quartic(w0, i0, z1, ratio, theta):
    """(35) as printed on `SALIENT` for each design: p, (34)'s left side at the angles
    `theta` (n, k), and the quartic in t = tan(theta / 2) (36)."""
    def one(w0, i0, z1, ratio, th):
        p = analysis.quartic_coefficients(w0, i0, _gains(SALIENT, w0, i0, z1, ratio),
                                          SALIENT)
        return p, analysis.trig_poly(p, th), analysis.quartic_t_coefficients(p)
    return jax.vmap(one)(w0, i0, z1, ratio, theta)


def test_printed_coefficients_vanish_at_the_general_roots():
    """(35) as printed: the left side of (34) is zero at every equilibrium found by the
    general route (so the printed p's are right up to a common factor)."""
    # 200 designs: the shapes of test_quartic_and_general_route_agree, whose program
    # gives the general route's equilibria
    w0, i0, z1, ratio = _random_designs(200, seed=2)
    eq = _both(_arr(SALIENT), w0, i0, z1, ratio, "observer")[1]
    assert np.all(np.asarray(eq.status) == 0)
    valid = np.asarray(eq.valid)
    P, V, C = map(np.asarray, _printed_quartic(w0, i0, z1, ratio,
                                               np.nan_to_num(np.asarray(eq.theta))))
    for k in range(len(w0)):
        p, th = P[k], np.asarray(eq.theta)[k][valid[k]]
        val = V[k][valid[k]]
        assert np.all(np.abs(val) < 1e-11 * np.max(np.abs(p)))
        # p5 = -p1 - p3, so t = 0 (theta = 0) is a root
        assert abs(p[4] + p[0] + p[2]) < 1e-14 * np.max(np.abs(p))
        c = C[k]
        t = np.tan(th[np.abs(th) > 1e-9] / 2)
        assert np.all(np.abs(np.polyval(c, t)) < 1e-9 * np.max(np.abs(c)) * (1 + t ** 4))


def _fal_mismatch_cases():
    mh1 = pj.PMSMParams(R_s=0.6, L_d=2.0e-3, L_q=3.2e-3, psi_f=0.05, n_p=5.0)
    mh2 = pj.PMSMParams(R_s=0.9, L_d=1.2e-3, L_q=2.0e-3, psi_f=0.06, n_p=5.0)
    return [
        dict(motor=M, motor_hat=None, a=0.5, eta=0.05 * 0.056),
        dict(motor=M, motor_hat=mh1, a=1.0, eta=1.0),
        dict(motor=SALIENT, motor_hat=mh2, a=1.0, eta=1.0),
        dict(motor=SALIENT, motor_hat=mh2, a=0.6, eta=0.003),
        dict(motor=SALIENT, motor_hat=None, a=0.3, eta=0.01),
    ]


@eqx.filter_jit
def _equilibria_jac_rhs(motor, mh, a, eta, w0, i0, z1, ratio):
    """One compiled function for every case: machines and fal parameters are traced (the
    fal path with a = 1 is the linear feedback), so the cases share one compilation."""
    def one(w0, i0, z1, ratio):
        g = _gains(mh, w0, i0, z1, ratio)
        eq = analysis.eso_equilibria(w0, i0, g, motor, mh, a=a, eta=eta, n_grid=128)
        x = jnp.nan_to_num(eq.x)
        A = jax.vmap(lambda x: analysis.eso_linearization(w0, i0, g, motor, mh, x=x, a=a,
                                                          eta=eta))(x)
        f = jax.vmap(lambda x: analysis.eso_rhs(x, w0, i0, g, motor, mh, a, eta))(x)
        return eq, A, f
    return jax.vmap(one)(w0, i0, z1, ratio)


@pytest.mark.parametrize("case", range(5))
def test_every_equilibrium_is_an_equilibrium_and_stability_matches_eigvals(case):
    c = _fal_mismatch_cases()[case]
    motor, mh, a, eta = c["motor"], c["motor_hat"], c["a"], c["eta"]
    n = 30
    w0, i0, z1, ratio = _random_designs(n, seed=10 + case)
    eq, A, f = _equilibria_jac_rhs(_arr(motor), _arr(motor if mh is None else mh),
                                   jnp.asarray(a), jnp.asarray(eta), w0, i0, z1, ratio)
    valid = np.asarray(eq.valid)
    # 0 ok, 2 no equilibrium at all (only with mismatch), never degenerate here
    assert np.all(np.asarray(eq.status) == np.where(np.asarray(eq.n) == 0, 2, 0))
    if mh is None:
        assert np.all(np.asarray(eq.n) >= 1)  # the origin
    else:  # with mismatch some operating points have no equilibrium at all
        assert np.mean(np.asarray(eq.n) >= 1) > 0.5
    assert np.nanmax(np.asarray(eq.residual)) < 1e-10
    # raw residual in SI, relative to the size of the terms
    scale = np.abs(np.asarray(w0))[:, None, None] * np.array(
        [0.056, 0.056, 1.0, DRIVE.w_rated])
    assert np.all((np.abs(np.asarray(f)) / scale)[valid] < 1e-9)
    ev = np.max(np.linalg.eigvals(np.asarray(A)).real, -1)
    marg = np.abs(ev) < 1e-9 * np.abs(np.asarray(w0))[:, None]
    check = valid & ~marg
    np.testing.assert_array_equal(np.asarray(eq.stable)[check], ev[check] < 0)
    assert np.any(np.asarray(eq.stable)[check]) and not np.all(np.asarray(eq.stable)[check])
    if mh is None:  # matched: the designed equilibrium is exactly the origin
        th0 = np.asarray(eq.theta)[np.arange(n), np.asarray(eq.principal)]
        np.testing.assert_allclose(th0, 0.0, atol=1e-10)


def test_close_pair_detected_on_a_coarse_grid():
    """Near the 1 <-> 3 transition two nonzero equilibria are closer than a grid step;
    the extremum splitting still finds them (n_grid = 16 is very coarse)."""
    w0 = 0.5 * DRIVE.w_rated
    i0 = jnp.array([0.0, 2.0]) * DRIVE.base.I_b
    z1s, ratios = np.linspace(0.05, 5.0, 40), np.linspace(0.05, 2.0, 40)
    n = np.asarray(analysis.classify_designs(SALIENT, w0, i0, z1s[:, None], ratios).n_nonzero)
    iz, ir = np.argwhere((n[:, :-1] == 1) & (n[:, 1:] == 3))[0]
    z1, lo, hi = z1s[iz], ratios[ir], ratios[ir + 1]
    # narrow [lo, hi] to 0.05 / 39^5 = 6e-10 by 40-point sections (the grid's program:
    # the same shapes), as 24 halvings would (3e-9): the pair's separation ~ sqrt(hi - lo)
    # is then small, but not rounding level
    for _ in range(5):
        r = np.linspace(lo, hi, 40)
        n = np.asarray(analysis.classify_designs(SALIENT, w0, i0, np.full((40, 1), z1),
                                                 r).n_nonzero)[0]
        j = int(np.argmax(n != 1))
        assert n[0] == 1 and j > 0 and n[j] == 3, n
        lo, hi = r[j - 1], r[j]
    g = _gains(SALIENT, w0, i0, z1, hi)
    ref = analysis.quartic_equilibria(w0, i0, g, SALIENT)
    assert int(ref.n) == 4
    th = np.sort(np.asarray(ref.theta)[np.asarray(ref.valid)])
    assert 1e-6 < np.min(np.diff(th)) < 2 * math.pi / 16  # a pair inside one grid step
    eq = analysis.eso_equilibria(w0, i0, g, SALIENT, n_grid=16)
    assert int(eq.status) == 0
    got = np.sort(np.asarray(eq.theta)[np.asarray(eq.valid)])
    assert len(got) == 4
    np.testing.assert_allclose(got, th, atol=1e-6)


def test_linearization_at_origin_is_the_matrix_15():
    # one compiled program per feedback (op by op: about 70 small ones); `a` and `eta`
    # stay Python numbers, as a user passes them (a = 1.0 selects the linear feedback)
    @functools.partial(jax.jit, static_argnums=(0, 1))
    def both(a, eta):
        w0 = 0.3 * DRIVE.w_rated
        i0 = jnp.array([-0.3, 0.8]) * DRIVE.base.I_b
        g = _gains(M, w0, i0, 1.7, 0.9)
        return (analysis.eso_linearization(w0, i0, g, M, a=a, eta=eta),
                error_matrix(w0, psi_a(M, i0), g))

    for a, eta in [(1.0, 1.0), (0.5, 0.003)]:
        A, want = map(np.asarray, both(a, eta))
        np.testing.assert_allclose(A, want, rtol=1e-12, atol=1e-9)


def test_linearize_vmaps_over_operating_points_and_designs():
    speeds = jnp.linspace(0.1, 1.0, 5) * DRIVE.w_rated
    z1 = jnp.array([0.5, 1.0, 2.0])
    i0 = jnp.array([0.0, 1.0]) * DRIVE.base.I_b

    def A(w0, z):
        g = _gains(M, w0, i0, z, 0.8)
        return analysis.linearize(analysis.eso_rhs, jnp.zeros(4), w0, i0, g, M)

    @jax.jit  # one program (op by op, the vmapped Jacobian compiled about 80 small ones)
    def poles(speeds, z1):
        As = jax.vmap(lambda w: jax.vmap(lambda z: A(w, z))(z1))(speeds)
        return As, analysis.charpoly(As)

    As, c = map(np.asarray, poles(speeds, z1))
    assert As.shape == (5, 3, 4, 4)
    # designed poles: flux s^2 + 2 z1 w1 s + w1^2, speed s^2 + 2 w2 s + w2^2
    w1 = 0.8 * np.asarray(speeds)[:, None]
    flux = np.stack([np.ones_like(w1 * z1), 2 * np.asarray(z1) * w1, w1 ** 2 + 0 * z1], -1)
    speed = np.array([1.0, 2 * W2, W2 ** 2])
    expect = np.stack([np.polymul(f, speed) for f in flux.reshape(-1, 3)]).reshape(c.shape)
    np.testing.assert_allclose(c, expect, rtol=1e-9)


@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_routh_hurwitz_matches_eigenvalues(n, getkey):
    @jax.jit  # one program per size (op by op: about 20 small ones)
    def check(key):
        A = jax.random.normal(key, (4000, n, n)) - 0.6 * jnp.eye(n)
        return A, analysis.charpoly(A), analysis.is_hurwitz(A), analysis.max_real_eig(A)

    A, c, rh, ev = map(np.asarray, check(getkey()))
    np.testing.assert_allclose(c, np.stack([np.poly(a) for a in A]), rtol=1e-9,
                               atol=1e-9)
    far = np.abs(ev) > 1e-8
    np.testing.assert_array_equal(rh[far], ev[far] < 0)
    assert 0.05 < rh.mean() < 0.95  # both outcomes are exercised


def test_equilibria_do_not_depend_on_the_speed_gains():
    # zhang2022 §IV: at an equilibrium g3 f = 0, so the equilibria do not depend on the
    # speed/angle gains g2, g3 (only their stability does). The quartic route never reads
    # g2, g3, so the claim is checked with the generic route, which solves the full error
    # dynamics (speed and angle rows included) of observers with different (zeta2, w2);
    # the Jacobians at the equilibria must differ, or the route did not read the gains.
    w0 = 0.5 * DRIVE.w_rated
    i0 = jnp.array([0.0, 2.0]) * DRIVE.base.I_b
    th, jac = [], []
    for zeta2, w2 in [(1.0, W2), (0.5, 50.0), (3.0, 3000.0)]:
        obs = pj.LESOObserver(SALIENT, pj.observers.ESODesign.fixed_ratio(0.4, 1.3, w2=w2,
                                                                          zeta2=zeta2))
        eq = analysis.equilibria(obs, SALIENT, w0, i0, method="generic")
        assert int(eq.status) == 0
        v = np.asarray(eq.valid)
        th.append(np.sort(np.asarray(eq.theta)[v]))
        jac.append(np.asarray(eq.jacobian)[v][np.argsort(np.asarray(eq.theta)[v])])
    q = analysis.quartic_equilibria(w0, i0, _gains(SALIENT, w0, i0, 0.4, 1.3), SALIENT)
    ref = np.sort(np.asarray(q.theta)[np.asarray(q.valid)])
    assert len(th[0]) >= 2  # the origin and at least one other equilibrium
    for t in th:
        np.testing.assert_allclose(t, ref, atol=1e-9)
    assert np.abs(jac[0] - jac[1]).max() > 1.0 and np.abs(jac[0] - jac[2]).max() > 1.0


def test_degenerate_points_report_status_not_errors():
    # (the grid of test_close_pair_detected_on_a_coarse_grid, and its program: these
    # statuses come from the reduction, before any grid)
    kw = dict(n_grid=16)
    i0 = jnp.zeros(2)
    g = _gains(M, 100.0, i0, 1.0, 1.0)
    eq = analysis.eso_equilibria(0.0, i0, g, M, **kw)  # w0 = 0
    assert int(eq.status) == -1
    g0 = _gains(M, 100.0, i0, 1.0, 0.0)  # w1 = 0: det(w0 J + G1) = 0
    assert int(analysis.eso_equilibria(100.0, i0, g0, M, **kw).status) == -1
    gn = _gains(M, 100.0, i0, 1.0, 1.0)
    gn = eqx.tree_at(lambda g: g.G1, gn, gn.G1 * jnp.nan)
    assert int(analysis.eso_equilibria(100.0, i0, gn, M, **kw).status) == -1


def test_bad_arguments_raise():
    g = _gains(M, 100.0, jnp.zeros(2), 1.0, 1.0)
    with pytest.raises(ValueError, match="n_grid"):
        analysis.eso_equilibria(100.0, jnp.zeros(2), g, M, n_grid=4)
    with pytest.raises(ValueError, match="frame"):
        analysis.eso_equilibria(100.0, jnp.zeros(2), g, M, frame="estimator")
    with pytest.raises(ValueError, match="frame"):
        analysis.eso_rhs(jnp.zeros(4), 100.0, jnp.zeros(2), g, M, frame="x")


@pytest.mark.parametrize("m", [1, 2, 5, 9, 10])
def test_generic_routes_small_linear_algebra(m):
    """The generic route's Cholesky solve and pivoted determinant (loops over the size,
    for the compile time) against NumPy, for the sizes of the registry's observers, with
    rows that need pivoting, a singular matrix, and under vmap."""
    from pmsmjax.analysis._scaled import _chol_solve, _det

    rng = np.random.default_rng(m)
    B = rng.normal(size=(m, m))
    H = B @ B.T + 0.1 * np.eye(m)
    g = rng.normal(size=m)
    x, logdet = jax.jit(_chol_solve)(jnp.asarray(H), jnp.asarray(g))
    np.testing.assert_allclose(x, np.linalg.solve(H, g), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(H)[1], rtol=1e-12, atol=1e-12)
    Ms = np.stack([rng.normal(size=(m, m)) for _ in range(4)])
    Ms[1, 0] = 0.0  # the first pivot is elsewhere
    Ms[2, -1] = Ms[2, 0]  # singular (for m > 1)
    d = jax.jit(jax.vmap(_det))(jnp.asarray(Ms))
    np.testing.assert_allclose(d, np.linalg.det(Ms), rtol=1e-10, atol=1e-12)


def test_fal_reduction_solve_and_its_derivative():
    """The fal reduction's inner solve s(u.b) (a safeguarded Newton that stops at rounding
    level, differentiated through one Newton step from its root): phi(s) = 0 to rounding
    on a dense angle grid, also where the root is the end of the starting bracket (fal's
    linear zone), and dr/dtheta by jax.grad equals central differences."""
    from pmsmjax.analysis._equilibria import _make_reduction

    m, mh = SALIENT, pj.scale_motor(SALIENT, {"R_s": 1.2, "L_q": 0.8, "psi_f": 0.9})
    w0, i0 = 0.4 * float(DRIVE.w_rated), jnp.array([0.5, 3.0])
    obs = pj.ESOObserver(mh, pj.ESODesign.zhang38(DRIVE.w_rated), a=0.6, eta=0.05 * m.psi_f)
    red, ok = _make_reduction(jnp.float64(w0), i0, obs.linear_gains(w0, i0), m, mh,
                              jnp.float64(0.6), jnp.float64(0.05 * m.psi_f), False)
    assert bool(ok)
    h = 1e-6

    @jax.jit  # one program (op by op, the loops would compile per call)
    def check(th):
        ub = jax.vmap(lambda t: jnp.dot(red.u, red.b(t)))(th)
        s = jax.vmap(red.s_of)(ub)
        phi = jax.vmap(lambda s_, ub_: jnp.dot(red.u, red.c(s_)) - ub_)(s, ub)
        lin = jnp.all(jnp.abs(s[:, None] * red.u) <= red.eta, axis=-1)
        t = th[::50]
        g = jax.vmap(jax.grad(red.r))(t)
        fd = (jax.vmap(red.r)(t + h) - jax.vmap(red.r)(t - h)) / (2 * h)
        return jnp.max(jnp.abs(phi) / (jnp.abs(ub) + jnp.abs(s))), lin, g, fd

    rel, lin, g, fd = check(jnp.linspace(-math.pi, math.pi, 2001))
    assert float(rel) < 1e-13
    # both regimes occur: roots inside fal's linear zone (|s u_k| eta^(a-1) <= eta^a for
    # both k) and outside it
    assert bool(jnp.any(lin)) and bool(jnp.any(~lin))
    # dr/dtheta against central differences
    np.testing.assert_allclose(np.asarray(g), np.asarray(fd), rtol=1e-6,
                               atol=1e-6 * float(jnp.max(jnp.abs(fd))))


def _scipy_equilibria(obs, plant, w, i0, n_theta=72):
    """Every equilibrium of `obs`'s error dynamics that SciPy's root finder (MINPACK
    hybrj, its own Newton-type iteration) reaches from a grid of angles, each with three
    starts for the other coordinates: the angles (rad, sorted) and whether each is stable
    by NumPy's eigenvalues of a central-difference Jacobian."""
    from scipy.optimize import fsolve

    from pmsmjax.observers._base import OperatingPoint

    op = OperatingPoint(jnp.asarray(w), jnp.asarray(i0))
    sc = np.asarray(obs.error_scale(op, plant))
    a = obs.coordinates.angle
    f = jax.jit(lambda z: obs.error_rhs(z * sc, op, plant) / sc / abs(w))  # keeps signs

    def jac(z, h=1e-6):
        cols = [(np.asarray(f(z + h * e)) - np.asarray(f(z - h * e))) / (2 * h)
                for e in np.eye(z.size)]
        return np.stack(cols, 1)

    found = []
    for th in np.linspace(-np.pi, np.pi, n_theta, endpoint=False):
        for y0 in (-1.0, 0.0, 1.0):
            z0 = np.full(sc.size, y0)
            z0[a] = th
            z, _, ier, _ = fsolve(lambda v: np.asarray(f(v)), z0, full_output=True,
                                  xtol=1e-13)
            if ier != 1 or np.max(np.abs(np.asarray(f(z)))) > 1e-10:
                continue
            t = np.pi - (np.pi - z[a]) % (2 * np.pi)  # in (-pi, pi], as the analysis's
            if all(abs((t - q + np.pi) % (2 * np.pi) - np.pi) > 1e-6 for q, _ in found):
                found.append((t, bool(np.all(np.linalg.eigvals(jac(z)).real < 0))))
    found.sort()
    return np.array([t for t, _ in found]), np.array([s for _, s in found])


@pytest.mark.parametrize("ratio", [0.9, 1.25])
def test_generic_route_finds_the_equilibria_off_its_branch(ratio):
    """The rotor-flux observer with its L_q off by `ratio` (morawiec_ipm3k5, 0.5 p.u.,
    i_q = 0.3 p.u.): the inner problem of the generic route has two branches and its
    residual jumps between them (the point was reported degenerate; with the jump taken
    for a zero, one equilibrium was missing and the designed one with it at 1.25). Every
    equilibrium against SciPy's root finder from 216 starts, stability against NumPy's
    eigenvalues."""
    drive = pj.preset("morawiec_ipm3k5")
    obs = pj.observers.make_observer("rotor-flux", drive)
    obs = obs.with_motor(pj.scale_motor(obs.motor, {"L_q": ratio}))
    w = 0.5 * float(drive.w_rated)
    i0 = np.array([0.0, 0.3 * float(drive.base.I_b)])
    # without the grid's Newton starts the point is degenerate, not wrong; the class
    # asks for them (`equilibria_starts`), so the default call searches the other branch
    assert int(analysis.equilibria(obs, drive.three_phase_motor, w, i0,
                                   n_starts=0).status) == -1
    eq = analysis.equilibria(obs, drive.three_phase_motor, w, i0)
    assert int(eq.status) == 0
    valid = np.asarray(eq.valid)
    theta, stable = np.asarray(eq.theta)[valid], np.asarray(eq.stable)[valid]
    ref_theta, ref_stable = _scipy_equilibria(obs, drive.three_phase_motor, w, i0)
    assert len(ref_theta) == 2  # the designed one near 0 and one far from it
    np.testing.assert_allclose(theta, ref_theta, atol=1e-9)
    np.testing.assert_array_equal(stable, ref_stable)


def test_rotor_flux_equilibria_with_a_matched_model_under_load():
    """The rotor-flux observer with its model matched (morawiec_ipm3k5, 0.5 and 0.8 p.u.,
    i_q for 0.4 p.u. of rated torque): the inner problem shows two branches here too, so
    without the Newton starts both points are degenerate; with the class's default
    (`equilibria_starts`) the designed equilibrium is found at zero angle error, exactly
    where a matched model puts it, and stable. One `analysis.equilibria` call per point
    and setting: the two programs of `test_generic_route_finds_the_equilibria_off_its_branch`
    (the same observer class and machine; its values are traced), not two of its own."""
    drive = pj.preset("morawiec_ipm3k5")
    m = drive.three_phase_motor
    obs = pj.observers.make_observer("rotor-flux", drive)
    i_q = 0.4 * float(drive.tau_rated) / (1.5 * float(m.n_p) * float(m.psi_f))
    i0 = np.array([0.0, i_q])
    for s in (0.5, 0.8):
        w = s * float(drive.w_rated)
        assert int(analysis.equilibria(obs, m, w, i0, n_starts=0).status) == -1
        eq = analysis.equilibria(obs, m, w, i0)
        assert int(eq.status) == 0
        p = int(eq.principal)
        assert abs(float(eq.theta[p])) <= 1e-9, s
        assert bool(eq.stable[p]), s
    # a wrapper (the speed from the angle) asks for what the wrapped observer asks for
    assert pj.SpeedFromAngle(obs, w_track=2 * math.pi * 30.0).equilibria_starts is True
    assert pj.observers.make_observer("eso", drive).equilibria_starts is False


def test_fa_leso_equilibria_with_a_nonaffine_inner_problem():
    """The FA-LESO (li-fa-leso (25)) on `zhang750` at 0.05 p.u. under rated load, with a
    design the comparison's tuner chose (k1 = 208 1/s^2, k2 = 1942 1/s, w_pll = 955
    rad/s, zeta_pll = 0.6): its resonator turns at the speed estimate, a coordinate of
    the error, so the inner solve is not affine. With three Gauss-Newton steps most grid
    angles stay unsettled and the point has no verdict; the class's default
    (`equilibria_gauss_newton`) settles them. Every equilibrium against SciPy's root
    finder from 216 starts, stability against NumPy's eigenvalues."""
    drive = pj.preset("zhang750")
    m = drive.three_phase_motor
    obs = pj.observers.make_observer("fa-leso", drive).with_design(
        k1=207.55679265261506, k2=1942.3143145197996, w_pll=955.4090984888849,
        zeta_pll=0.6002345256425745)
    w = 0.05 * float(drive.w_rated)
    i0 = np.array([0.0, float(drive.tau_rated) / (float(drive.k_tau) * float(m.psi_f))])
    assert obs.equilibria_gauss_newton > 3
    assert int(analysis.equilibria(obs, m, w, i0, n_gauss_newton=3).status) == -1
    eq = analysis.equilibria(obs, m, w, i0)
    assert int(eq.status) == 0
    valid = np.asarray(eq.valid)
    theta, stable = np.asarray(eq.theta)[valid], np.asarray(eq.stable)[valid]
    ref_theta, ref_stable = _scipy_equilibria(obs, m, w, i0)
    np.testing.assert_allclose(theta, ref_theta, atol=1e-9)
    np.testing.assert_array_equal(stable, ref_stable)
    # the designed one (a matched model: zero angle error) stable, the other not
    assert abs(theta[int(np.argmin(np.abs(theta)))]) < 1e-9 and stable.sum() == 1
    with pytest.raises(ValueError, match="n_gauss_newton"):
        analysis.equilibria(obs, m, w, i0, n_gauss_newton=0)


def test_rotor_flux_equilibria_that_three_inner_steps_miss():
    """The rotor-flux observer (morawiec_ipm3k5, 0.1 p.u., no load) with its R_s at x0.7:
    with three Gauss-Newton steps of the inner solve the generic route found three
    equilibria and missed a stable one at -23 deg, so the point read as feasible (the
    designed equilibrium the only stable one); with the class's default
    (`equilibria_gauss_newton`) it finds all four. Every equilibrium against SciPy's
    root finder from 216 starts, stability against NumPy's eigenvalues."""
    drive = pj.preset("morawiec_ipm3k5")
    m = drive.three_phase_motor
    obs = pj.observers.make_observer("rotor-flux", drive)
    obs = obs.with_motor(pj.scale_motor(obs.motor, {"R_s": 0.7}))
    w, i0 = 0.1 * float(drive.w_rated), np.zeros(2)
    ref_theta, ref_stable = _scipy_equilibria(obs, m, w, i0)
    assert len(ref_theta) == 4 and ref_stable.sum() == 2
    three = analysis.equilibria(obs, m, w, i0, n_gauss_newton=3)
    assert int(three.status) == 0 and int(three.n) == 3
    eq = analysis.equilibria(obs, m, w, i0)
    assert int(eq.status) == 0
    valid = np.asarray(eq.valid)
    np.testing.assert_allclose(np.asarray(eq.theta)[valid], ref_theta, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(eq.stable)[valid], ref_stable)
    # a wrapper (the speed from the angle) asks for what the wrapped observer asks for
    assert pj.SpeedFromAngle(obs, w_track=2 * math.pi * 30.0).equilibria_gauss_newton == 8
