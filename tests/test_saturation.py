"""Saturated machines: the magnetic models, the plant on a flux map and the saturated preset.

References used here are independent of the code under test: the analytical model a map
was sampled from, the flux-linkage form of the machine equations integrated by SciPy with
the map inverted by SciPy's root finder, the magnetic energy of the model, and the
constant-inductance plant.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize

import pmsmjax as pj


I_MAX = 7.5 * math.sqrt(2.0)


def _sat():
    return pj.ipm3k5_saturation()


def _constant_as_model(motor):
    """The constant-inductance machine as an `AlgebraicSaturation` (no saturation terms)."""
    return pj.AlgebraicSaturation(a_d0=1 / motor.L_d, a_dd=0.0, a_q0=1 / motor.L_q,
                                  a_qq=0.0, a_dq=0.0, i_f=motor.psi_f / motor.L_d)


def _with_magnetic(drive, model):
    return eqx.tree_at(lambda d: d.motor.magnetic, drive, model, is_leaf=lambda x: x is None)


def test_preset_targets():
    """The five design targets stated in `ipm3k5_saturation`'s docstring."""
    m, drive = _sat(), pj.preset("morawiec_ipm3k5")
    L_d, L_q, psi_f = pj.constant_model(m)
    assert L_d == pytest.approx(drive.motor.L_d, rel=1e-9)
    assert L_q == pytest.approx(drive.motor.L_q, rel=1e-9)
    assert psi_f == pytest.approx(drive.motor.psi_f, rel=1e-9)
    L_d_app, L_q_app, psi_f_load = m.apparent_inductance(jnp.array([0.0, I_MAX]))
    assert float(L_q_app) / L_q == pytest.approx(0.6, abs=1e-6)
    assert float(psi_f_load) / psi_f == pytest.approx(0.95, abs=1e-6)
    g_dd, _, _ = m._hessian(psi_f, 0.0)
    assert (m.S + 1) * m.a_dd * psi_f ** m.S / float(g_dd) == pytest.approx(0.3, abs=1e-9)


def test_inversion_converges_and_is_reciprocal():
    """Newton's continuation inverts the model to the last digits over 3 i_max, the
    incremental inductance is the inverse of the energy's Hessian (finite differences of
    the explicit current) and symmetric (reciprocal)."""
    m = _sat()
    g = jnp.linspace(-3 * I_MAX, 3 * I_MAX, 61)
    dd, qq = jnp.meshgrid(g, g, indexing="ij")
    psi_d, psi_q, l_dd, l_dq, l_qd, l_qq = m.flux_and_inductance(dd, qq)
    r_d, r_q = m.current(psi_d, psi_q)
    assert float(jnp.max(jnp.abs(r_d - dd) + jnp.abs(r_q - qq))) < 1e-11
    np.testing.assert_allclose(l_dq, l_qd, rtol=0, atol=1e-15)
    # d i / d psi by central differences of the explicit model, inverted
    eps = 1e-6
    k = (17, 44)
    p = np.array([float(psi_d[k]), float(psi_q[k])])
    jac = np.zeros((2, 2))
    for j in range(2):
        dp = np.zeros(2)
        dp[j] = eps
        hi = np.array([float(x) for x in m.current(*(p + dp))])
        lo = np.array([float(x) for x in m.current(*(p - dp))])
        jac[:, j] = (hi - lo) / (2 * eps)
    L = np.linalg.inv(jac)
    np.testing.assert_allclose([[l_dd[k], l_dq[k]], [l_qd[k], l_qq[k]]], L, rtol=1e-7)


def test_map_interpolation_order():
    """A map sampled from the analytical model converges to it at the spline's order: the
    error's slope against the grid spacing over 17..129 points per axis is about 4 for
    the flux (fitted: at least 3.5) and about 3 for the incremental inductance (at least
    2.7); measured 4.4 and 3.6 (coarser grids are not yet asymptotic)."""
    m = _sat()
    g_d = np.linspace(-1.5 * I_MAX, 0.0, 37)
    g_q = np.linspace(-1.5 * I_MAX, 1.5 * I_MAX, 41)
    x = jnp.stack(jnp.meshgrid(g_d, g_q, indexing="ij"), -1)
    psi_ref, l_ref = m.flux_dq(x), m.incremental_inductance(x)
    ns = np.array([17, 33, 65, 129])
    e_psi, e_l = [], []
    for k in ns:
        fm = m.sample(np.linspace(-2 * I_MAX, 0.5 * I_MAX, k),
                      np.linspace(-2 * I_MAX, 2 * I_MAX, k))
        e_psi.append(float(jnp.max(jnp.abs(fm.flux_dq(x) - psi_ref))))
        e_l.append(float(jnp.max(jnp.abs(fm.incremental_inductance(x) - l_ref))))
    h = 1.0 / (ns - 1)
    order_psi = np.polyfit(np.log(h), np.log(e_psi), 1)[0]
    order_l = np.polyfit(np.log(h), np.log(e_l), 1)[0]
    assert order_psi > 3.5, (order_psi, e_psi)
    assert order_l > 2.7, (order_l, e_l)


def test_map_extends_linearly_and_is_differentiable():
    """Outside the grid the flux continues with the edge's incremental inductance; the
    interpolant's derivative (jax.jacfwd) equals its incremental inductance inside."""
    fm = pj.preset("ipm3k5_sat").motor.magnetic
    edge = jnp.array([float(fm.i_d[-1]), 3.0])
    out = edge + jnp.array([4.0, 0.0])
    L = fm.incremental_inductance(edge)
    np.testing.assert_allclose(fm.flux_dq(out), fm.flux_dq(edge) + L @ jnp.array([4.0, 0.0]),
                               rtol=1e-12)
    x = jnp.array([-4.3, 6.1])
    np.testing.assert_allclose(jax.jacfwd(fm.flux_dq)(x), fm.incremental_inductance(x),
                               rtol=1e-10)


def test_single_runs_and_batches_evaluate_the_same_map():
    """A flux map has two layouts (pmsmjax._sim._batching.by_batch): the per-cell table
    product for a single run and a batch of one, Horner's scheme for a batch. Both give
    the same flux and inductances to 1e-12 (relative) at random currents inside and
    outside the grid, unbatched, under `vmap` of one, of five and nested; the programs
    are the ones the rule says (a sum over the 16 monomials only in the table product);
    forward and reverse derivatives agree with central differences."""
    fm = pj.preset("ipm3k5_sat").motor.magnetic
    x = jax.random.uniform(jax.random.PRNGKey(3), (5, 2), minval=-1.7 * I_MAX,
                           maxval=1.7 * I_MAX)
    ev = lambda i: jnp.stack(fm.flux_and_inductance(i[..., 0], i[..., 1]), -1)  # noqa: E731
    # the reference: NumPy's polynomial evaluation of each cell's coefficients, point by
    # point in a plain loop
    P = np.polynomial.polynomial
    cells = np.asarray(fm._cells)
    ref = []
    g_d, g_q = np.asarray(fm.i_d), np.asarray(fm.i_q)  # the grid, in NumPy
    for i_d, i_q in np.asarray(x):
        d = min(max(i_d, float(g_d[0])), float(g_d[-1]))
        q = min(max(i_q, float(g_q[0])), float(g_q[-1]))
        hd, hq = float(g_d[1] - g_d[0]), float(g_q[1] - g_q[0])
        kd = min(int((d - float(g_d[0])) // hd), g_d.shape[0] - 2)
        kq = min(int((q - float(g_q[0])) // hq), g_q.shape[0] - 2)
        t, u = (d - float(g_d[kd])) / hd, (q - float(g_q[kq])) / hq
        c = cells[kd, kq]
        f_d, f_q = (P.polyval2d(t, u, c[x]) for x in (0, 1))
        l_dd, l_qd = (P.polyval2d(t, u, P.polyder(c[x], axis=0)) / hd for x in (0, 1))
        l_dq, l_qq = (P.polyval2d(t, u, P.polyder(c[x], axis=1)) / hq for x in (0, 1))
        ref.append([f_d + l_dd * (i_d - d) + l_dq * (i_q - q),
                    f_q + l_qd * (i_d - d) + l_qq * (i_q - q), l_dd, l_dq, l_qd, l_qq])
    ref = np.asarray(ref)
    # each layout compiled once (jit picks the layout as the eager call does: by the
    # batch of the traced call), instead of an eager program per operation
    xn = np.asarray(x)
    ev1, evb = jax.jit(ev), jax.jit(jax.vmap(ev))
    runs = {"unbatched": np.stack([ev1(i) for i in xn]), "batch of 5": evb(xn),
            "batch of 1": np.concatenate([evb(i[None]) for i in xn]),
            "nested": np.asarray(jax.jit(jax.vmap(jax.vmap(ev)))(xn[:, None])).reshape(5, 6)}
    for name, out in runs.items():
        np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-15, err_msg=name)

    def sums(f, *a):
        return str(jax.make_jaxpr(f)(*a)).count("reduce_sum")

    assert sums(ev, x[0]) >= 1 and sums(jax.vmap(ev), x[:1]) >= 1
    assert sums(jax.vmap(ev), x) == 0 and sums(jax.vmap(jax.vmap(ev)), x[:, None]) == 0
    psi = lambda i: jnp.sum(ev(i)[:2] ** 2)  # noqa: E731
    h = 1e-6
    psi_j, grad_j, jacfwd_j = jax.jit(psi), jax.jit(jax.grad(psi)), jax.jit(jax.jacfwd(psi))
    for i in xn[:3]:
        fd = np.array([(float(psi_j(i + h * e)) - float(psi_j(i - h * e))) / (2 * h)
                       for e in np.eye(2)])
        np.testing.assert_allclose(grad_j(i), fd, rtol=1e-6)
        np.testing.assert_allclose(jacfwd_j(i), fd, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(psi)))(xn[:3]),
                               np.stack([grad_j(i) for i in xn[:3]]), rtol=1e-12)


def test_constant_map_reproduces_the_constant_plant():
    """A map sampled from constant inductances gives the constant plant's vector field to
    rounding, and the same closed-loop run to 1e-9 A."""
    drive = pj.preset("morawiec_ipm3k5")
    lin = _constant_as_model(drive.motor).sample(np.linspace(-25, 10, 8),
                                                 np.linspace(-25, 25, 9))
    sat = _with_magnetic(drive, lin)
    y = pj.PlantState(i_dq=jnp.array([-3.0, 7.0]), theta=jnp.array(0.3), w_m=jnp.array(200.0))
    u = pj.PlantInput(u_ab=jnp.array([100.0, -50.0]), tau_L=jnp.array(1.0))
    a = pj.PMSM(drive.motor, drive.mechanics).vector_field(0.0, y, u)
    b = pj.PMSM(sat.motor, sat.mechanics).vector_field(0.0, y, u)
    np.testing.assert_allclose(b.i_dq, a.i_dq, rtol=1e-12)
    np.testing.assert_allclose(b.w_m, a.w_m, rtol=1e-12)


def test_energy_balance_on_the_analytical_model():
    """p_in - p_cu - p_mech equals the rate of the model's own magnetic energy W(psi)
    (computed from `energy`, not from the plant): the torque psi x i is the one energy
    conservation requires."""
    drive = _with_magnetic(pj.preset("morawiec_ipm3k5"), _sat())
    plant = pj.PMSM(drive.motor, drive.mechanics)
    rng = np.random.default_rng(1)
    m = drive.motor.magnetic
    for _ in range(5):
        i_dq = jnp.asarray(rng.uniform(-15, 15, 2))
        y = pj.PlantState(i_dq=i_dq, theta=jnp.asarray(rng.uniform(0, 6)),
                          w_m=jnp.asarray(rng.uniform(-300, 300)))
        u = pj.PlantInput(u_ab=jnp.asarray(rng.uniform(-200, 200, 2)), tau_L=jnp.array(0.0))
        p_in, p_cu, _, p_mech = plant.power_balance(y, u)
        di = plant.vector_field(0.0, y, u).i_dq

        def W(i):
            psi = m.flux_dq(i)
            return m.energy(psi[0], psi[1])

        dW = 1.5 * jnp.dot(jax.grad(W)(i_dq), di)
        assert float(p_in - p_cu - p_mech) == pytest.approx(float(dW), rel=1e-9, abs=1e-9)


def test_plant_against_scipy_flux_linkage_integration():
    """The plant on the preset's flux map (current as state, incremental inductance)
    against SciPy's RK45 of the flux-linkage form d psi/dt = u - R i - w J psi with the
    same map inverted by SciPy's root finder: 1.9e-11 of the peak current measured, at
    the integrators' tolerances."""
    import diffrax

    drive = pj.preset("ipm3k5_sat")
    fm, R = drive.motor.magnetic, float(drive.motor.R_s)
    w = 5.0  # held by a load machine
    u_ab = np.array([-8.0, 12.0])
    plant = pj.PMSM(drive.motor, drive.mechanics)
    y0 = pj.PlantState(i_dq=jnp.array([0.0, 0.0]), theta=jnp.array(0.0), w_m=jnp.array(w))
    args = pj.PlantInput(u_ab=jnp.asarray(u_ab), tau_L=jnp.array(0.0), free=0.0)
    ts = np.linspace(0.0, 0.1, 26)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(plant.vector_field), diffrax.Dopri8(), 0.0, 0.1, 1e-5, y0, args,
        saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12), max_steps=100000)

    flux_jit = jax.jit(lambda i: fm.flux_dq(i))

    def flux(i):
        return np.asarray(flux_jit(jnp.asarray(i)))

    def current(psi, guess):
        sol = scipy.optimize.root(lambda i: flux(i) - psi, guess, method="hybr",
                                  options={"xtol": 1e-15})
        assert np.max(np.abs(flux(sol.x) - psi)) < 1e-13
        return sol.x

    state = {"i": np.zeros(2)}

    def rhs(t, psi):
        th = w * t
        c, s = math.cos(th), math.sin(th)
        u_dq = np.array([c * u_ab[0] + s * u_ab[1], c * u_ab[1] - s * u_ab[0]])
        i = current(psi, state["i"])
        state["i"] = i
        return u_dq - R * i - w * np.array([-psi[1], psi[0]])

    ref = scipy.integrate.solve_ivp(rhs, (0.0, 0.1), flux(np.zeros(2)), method="RK45",
                                    t_eval=ts, rtol=1e-11, atol=1e-13)
    i_ref = np.array([current(p, np.zeros(2)) for p in ref.y.T])
    i_sim = np.asarray(sol.ys.i_dq)
    scale = np.max(np.abs(i_ref))
    assert scale > 5.0  # the run reaches saturating currents, inside the map's grid
    assert np.all(i_ref[:, 0] > float(fm.i_d[0])) and np.all(i_ref[:, 0] < float(fm.i_d[-1]))
    assert np.all(np.abs(i_ref[:, 1]) < float(fm.i_q[-1]))
    rel = np.max(np.abs(i_sim - i_ref)) / scale
    print(f"plant against SciPy's flux-linkage integration: {rel:.2e} of the peak current")
    assert rel < 1e-10  # measured 1.9e-11: the references' tolerances (rtol 1e-11, 1e-12)


def test_constant_model_choices():
    """small-current = zero-current incremental values; rated = apparent at i_max on the
    q axis; fit = least squares over the motoring region (checked by numpy's lstsq on the
    same points computed here)."""
    m = _sat()
    Ls = pj.constant_model(m, "small-current")
    Lr = pj.constant_model(m, "rated", I_MAX)
    Lf = pj.constant_model(m, "fit", I_MAX)
    psi = m.flux_dq(jnp.array([0.0, I_MAX]))
    assert Lr[1] == pytest.approx(float(psi[1]) / I_MAX, rel=1e-12)
    assert Lr[2] == pytest.approx(float(m.flux_dq(jnp.array([0.0, I_MAX]))[0]), rel=1e-12)
    assert Lr[1] < Lf[1] < Ls[1]  # the fit lies between no load and full load
    with pytest.raises(ValueError, match="how"):
        pj.constant_model(m, "average")
    with pytest.raises(ValueError, match="i_max"):
        pj.constant_model(m, "fit")


def test_flux_map_structure_errors():
    with pytest.raises(ValueError, match="at least 4"):
        pj.FluxMap([0, 1, 2], [0, 1, 2, 3], np.zeros((3, 4)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="shape"):
        pj.FluxMap([0, 1, 2, 3], [0, 1, 2, 3], np.zeros((4, 3)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="strictly increasing"):
        pj.FluxMap([0, 1, 1, 3], [0, 1, 2, 3], np.zeros((4, 4)), np.zeros((4, 4)))


def test_spline_is_scipys_not_a_knot_spline():
    """The map's interpolant along each axis is SciPy's not-a-knot cubic spline through
    the same values (on a non-uniform grid), for the flux and its derivative, and the
    traced (jax.numpy) construction equals the numpy one."""
    from scipy.interpolate import CubicSpline

    from pmsmjax._plant._magnetic import _bicubic_cells

    rng = np.random.default_rng(3)
    i_d = np.cumsum(rng.uniform(0.5, 1.5, 7)) - 8.0
    i_q = np.cumsum(rng.uniform(0.5, 1.5, 6)) - 3.0
    psi_d = rng.normal(size=(7, 6))
    psi_q = rng.normal(size=(7, 6))
    fm = pj.FluxMap(i_d, i_q, psi_d, psi_q)
    q0 = i_q[2]  # on a grid line in q the 2-D spline is the 1-D spline in d
    x = np.linspace(i_d[0], i_d[-1], 23)
    ref = CubicSpline(i_d, psi_d[:, 2], bc_type="not-a-knot")
    psi_d_hat, _, l_dd, *_ = fm.flux_and_inductance(jnp.asarray(x), jnp.full(23, q0))
    np.testing.assert_allclose(psi_d_hat, ref(x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(l_dd, ref(x, 1), rtol=0, atol=1e-11)
    f = np.stack([psi_d, psi_q], -1)
    traced = jax.jit(_bicubic_cells)(jnp.asarray(i_d), jnp.asarray(i_q), jnp.asarray(f))
    np.testing.assert_allclose(traced, _bicubic_cells(i_d, i_q, f), rtol=1e-12, atol=1e-12)
