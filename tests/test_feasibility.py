"""Feasibility maps (zhang2022 Fig. 1): closed form vs general route, Table I, an
infeasible case checked by simulation, error handling."""

import math

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import eso_gains, psi_a


DRIVE = pj.preset("zhang750")
M = DRIVE.motor
W2 = 2 * math.pi * 50
SALIENT = pj.PMSMParams(R_s=0.78, L_d=1.0e-3, L_q=4.9e-3, psi_f=0.056, n_p=5.0)
SALIENT_DRIVE = pj.replace_params(DRIVE, L_d=1.0e-3, L_q=4.9e-3)


def _random(n, seed):
    rng = np.random.default_rng(seed)
    w0 = rng.choice([-1.0, 1.0], n) * rng.uniform(0.02, 1.5, n) * DRIVE.w_rated
    i0 = rng.uniform(-2.0, 2.0, (n, 2)) * DRIVE.base.I_b
    return w0, i0, rng.uniform(0.0, 5.0, n), rng.uniform(0.02, 2.0, n)


@pytest.mark.parametrize("frame", ["observer", "paper"])
def test_closed_form_matches_general_route(frame):
    w0, i0, z1, r = _random(300, seed=3)
    for motor in (M, SALIENT):
        cf = analysis.classify_designs(motor, w0, i0, z1, r, frame=frame)
        ge = analysis.classify_designs(motor, w0, i0, z1, r, frame=frame, method="general",
                                       n_grid=128)
        np.testing.assert_array_equal(np.asarray(cf.status), np.asarray(ge.status))
        np.testing.assert_array_equal(np.asarray(cf.n_nonzero), np.asarray(ge.n_nonzero))
        a = np.sort(np.nan_to_num(np.asarray(cf.theta), nan=9.0), -1)
        b = np.sort(np.nan_to_num(np.asarray(ge.theta), nan=9.0), -1)[:, :3]
        np.testing.assert_allclose(a, b, atol=1e-9)
        np.testing.assert_allclose(np.asarray(cf.stable_theta), np.asarray(ge.stable_theta),
                                   atol=1e-9)
        np.testing.assert_array_equal(np.asarray(cf.principal_stable),
                                      np.asarray(ge.principal_stable))
        if motor is SALIENT:
            assert 0.02 < np.mean(np.asarray(cf.status) == 1) < 0.5


def test_table_I_is_feasible_everywhere_and_fig9_design():
    z1 = np.linspace(0.0, 5.0, 51)
    ratio = np.linspace(0.0, 2.0, 41)
    loads = [(0.0, 0.0), (0.0, 1.0), (0.0, 2.0), (-1.0, 1.0), (1.0, 2.0)]
    fm = analysis.feasibility_map(DRIVE, [0.01, 0.5, 1.0], z1, ratio, i_dq=loads)
    st = np.asarray(fm.status)
    assert st.shape == (3, 5, 51, 41)
    assert np.all(st[..., 0] == -1)  # ratio = 0: w1 = 0, degenerate
    assert np.all(st[..., 1:] == 0)  # Table I: every design is feasible
    assert np.all(np.asarray(fm.n_nonzero)[..., 1:] == 1)
    assert np.all(np.isnan(np.asarray(fm.stable_theta_deg)))
    assert np.all(np.asarray(fm.principal_stable)[:, :, 1:, 1:])  # zeta1 > 0
    z38, r38 = fm.schedule38()
    np.testing.assert_allclose(z38, [1.51, 2.0, 2.5])
    np.testing.assert_allclose(r38 * z38, 1.5)
    # Fig. 9's design at 0.5 p.u., no load: tan(theta/2) = w1 / (2 zeta1 w0) = 0.5
    c = analysis.classify_designs(M, 0.5 * DRIVE.w_rated, (0.0, 0.0), 0.5, 0.5)
    assert int(c.status) == 0 and int(c.n_nonzero) == 1
    np.testing.assert_allclose(np.degrees(float(c.theta[0])), 2 * np.degrees(np.arctan(0.5)),
                               atol=1e-9)
    assert "feasible 97.6%, infeasible 0.0%, degenerate 2.4%" in fm.summary().splitlines()[0]


# the error dynamics (11) with the operating point and gains as the solve's arguments
_TERM = dfx.ODETerm(lambda t, x, args: analysis.eso_rhs(x, *args))


def _simulate(motor, w0, i0, z1, ratio, x0, t1):
    g = eso_gains(psi_a(motor, i0), w0, z1, ratio * abs(w0), 1.0, W2)
    # the speed, current, gains and end time as arrays: every call one compiled solve
    sol = dfx.diffeqsolve(_TERM, dfx.Tsit5(), 0.0, jnp.asarray(t1), None, x0,
                          args=(jnp.asarray(w0), jnp.asarray(i0), g, motor),
                          stepsize_controller=dfx.PIDController(rtol=1e-9, atol=1e-11),
                          max_steps=200_000)
    return np.asarray(sol.ys[-1])


def test_infeasible_design_keeps_its_static_error_and_feasible_design_converges():
    w0, i0 = 0.5 * DRIVE.w_rated, jnp.array([0.0, 2.0]) * DRIVE.base.I_b
    z1 = np.linspace(0.05, 5.0, 30)
    ratio = np.linspace(0.05, 2.0, 30)
    c = analysis.classify_designs(SALIENT, w0, i0, z1[:, None], ratio)
    st = np.asarray(c.status)
    assert np.any(st == 1) and np.any(st == 0)
    # infeasible: start 2 deg from its stable nonzero equilibrium -> stays (static error)
    iz, ir = np.argwhere(st == 1)[0]
    g = eso_gains(psi_a(SALIENT, i0), w0, z1[iz], ratio[ir] * w0, 1.0, W2)
    eq = analysis.eso_equilibria(w0, i0, g, SALIENT)
    th_s = float(c.stable_theta[iz, ir])
    k = int(np.nanargmin(np.abs(np.asarray(eq.theta) - th_s)))
    assert bool(eq.stable[k])
    x_star = np.asarray(eq.x[k])
    # compiled (op by op, each of its some 50 small operations compiles on its own)
    A = jax.jit(analysis.eso_linearization)(w0, i0, g, SALIENT, x=eq.x[k])
    decay = -float(analysis.max_real_eig(A))
    assert decay > 0
    x_end = _simulate(SALIENT, w0, i0, z1[iz], ratio[ir],
                      jnp.asarray(x_star + np.array([0, 0, math.radians(2.0), 0])),
                      15.0 / decay)
    assert abs(pj.wrap_angle(x_end[2]) - th_s) < math.radians(0.01)
    assert abs(math.degrees(th_s)) > 10.0
    # feasible: start 2 deg from its (unstable) nonzero equilibrium -> converges to zero
    iz, ir = np.argwhere(st == 0)[len(np.argwhere(st == 0)) // 2]
    th_u = float(np.nanmin(np.asarray(c.theta[iz, ir])))
    g = eso_gains(psi_a(SALIENT, i0), w0, z1[iz], ratio[ir] * w0, 1.0, W2)
    eq = analysis.eso_equilibria(w0, i0, g, SALIENT)
    k = int(np.nanargmin(np.abs(np.asarray(eq.theta) - th_u)))
    assert not bool(eq.stable[k])
    x0 = np.asarray(eq.x[k]) + np.array([0, 0, -math.radians(2.0) * np.sign(th_u), 0])
    x_end = _simulate(SALIENT, w0, i0, z1[iz], ratio[ir], jnp.asarray(x0), 200.0 / w0)
    assert abs(pj.wrap_angle(x_end[2])) < math.radians(0.01)
    assert abs(x_end[3]) < 1e-3


def test_float32_agrees_with_float64():
    w0, i0, z1, r = _random(20000, seed=4)
    c64 = analysis.classify_designs(SALIENT, w0, i0, z1, r)
    c32 = analysis.classify_designs(SALIENT, w0, i0, z1, r, dtype=jnp.float32)
    assert c32.stable_theta.dtype == jnp.float32
    agree = np.mean(np.asarray(c64.status) == np.asarray(c32.status))
    assert agree > 0.999
    ok = np.asarray(c64.status) == np.asarray(c32.status)
    np.testing.assert_allclose(np.asarray(c32.stable_theta)[ok],
                               np.asarray(c64.stable_theta)[ok], atol=2e-3)


def test_general_route_map_with_mismatch_and_fal():
    # zhang2022's reduction (the map's "general" route) against the generic contract route
    # (constrained least squares on the observer's full error dynamics, another algorithm)
    # on every grid point: same status, same number of equilibria, same angles.
    mh = pj.PMSMParams(R_s=0.7, L_d=1.3e-3, L_q=4.0e-3, psi_f=0.06, n_p=5.0)
    zetas, ratios = [0.3, 1.0, 2.0], [0.3, 1.0]
    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.5], zetas, ratios,
                                  i_dq=(0.0, 1.0), motor_hat=mh, a=0.6, eta=0.003,
                                  n_grid=64)
    assert fm.method == "general"
    st = np.asarray(fm.status)
    assert st.shape == (1, 1, 3, 2)
    w0 = 0.5 * float(SALIENT_DRIVE.w_rated)
    i0 = jnp.array([0.0, 1.0]) * SALIENT_DRIVE.base.I_b
    for i, z1 in enumerate(zetas):
        for j, r in enumerate(ratios):
            obs = pj.ESOObserver(mh, pj.observers.ESODesign.fixed_ratio(z1, r, w2=W2),
                                 a=0.6, eta=0.003)
            ref = analysis.classify(obs, SALIENT, w0, i0, method="generic")
            assert st[0, 0, i, j] == int(ref.status), (z1, r)
            assert int(np.asarray(fm.n_nonzero)[0, 0, i, j]) == int(ref.n_nonzero)
            np.testing.assert_allclose(np.asarray(fm.principal_theta_deg)[0, 0, i, j],
                                       np.degrees(float(ref.principal_theta)), atol=1e-6)
    # the mismatch moves the designed equilibrium off zero (a static error)
    assert np.all(np.abs(np.asarray(fm.principal_theta_deg)) > 0.01)


def test_bad_grids_raise():
    z, r = np.linspace(0.1, 5, 4), np.linspace(0.1, 2, 3)
    with pytest.raises(ValueError, match="speeds.*empty"):
        analysis.feasibility_map(DRIVE, [], z, r)
    with pytest.raises(ValueError, match="zeta1.*finite"):
        analysis.feasibility_map(DRIVE, [0.5], [0.1, np.nan], r)
    with pytest.raises(ValueError, match=r"speeds.*must not contain 0"):
        analysis.feasibility_map(DRIVE, [0.0, 0.5], z, r)
    with pytest.raises(ValueError, match="ratio.*>= 0"):
        analysis.feasibility_map(DRIVE, [0.5], z, [-0.1, 1.0])
    with pytest.raises(ValueError, match="i_dq"):
        analysis.feasibility_map(DRIVE, [0.5], z, r, i_dq=[0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="method"):
        analysis.feasibility_map(DRIVE, [0.5], z, r, method="quartic")
    with pytest.raises(ValueError, match="closed_form.*motor_hat"):
        analysis.feasibility_map(DRIVE, [0.5], z, r, method="closed_form", motor_hat=M)
    with pytest.raises(ValueError, match="frame"):
        analysis.feasibility_map(DRIVE, [0.5], z, r, frame="rotor")
    with pytest.raises(ValueError, match="drive"):
        analysis.feasibility_map(M, [0.5], z, r)
    # standstill is a status, not an error: the gains (17) contain w1^2/w0
    st = analysis.classify_designs(M, [0.0, 10.0], (0.0, 0.0), 1.0, 1.0).status
    np.testing.assert_array_equal(np.asarray(st), [-1, 0])


def test_bad_points_under_vmap_give_status_not_nan():
    f = jax.jit(jax.vmap(lambda w0, z1: analysis.classify_designs(M, w0, (0.0, 1.0), z1,
                                                                  0.8).status))
    st = np.asarray(f(jnp.array([0.0, 100.0, jnp.nan, 100.0]),
                      jnp.array([1.0, 1.0, 1.0, jnp.nan])))
    np.testing.assert_array_equal(st, [-1, 0, -1, -1])


def test_plot_helper_draws_overlaid_speeds(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from pmsmjax.plotting import plot_feasibility

    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.01, 0.5, 1.0], np.linspace(0, 5, 26),
                                  np.linspace(0, 2, 21), i_dq=(0.0, 2.0))
    ax = plot_feasibility(fm)
    assert len(ax.get_legend().get_texts()) >= 4  # three speeds + the (38) schedule
    ax.figure.savefig(tmp_path / "map.png")
    assert (tmp_path / "map.png").stat().st_size > 1000
