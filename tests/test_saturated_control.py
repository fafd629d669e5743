"""Control on a saturated machine (`pmsmjax._control._saturated`): MTPA from the map against
a brute-force search, the map of constant inductances against `mtpa_i_d`, the current
controller's gains against finite differences of the map, the constant path unchanged,
and closed-loop runs of the `"ipm3k5_sat"` preset (torque reached at 0.8 p.u. load,
voltage limit kept in field weakening)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj


DRIVE = pj.preset("ipm3k5_sat")
MOTOR = DRIVE.motor
MAG = MOTOR.magnetic
K = float(DRIVE.k_tau)
I_MAX = float(DRIVE.i_max)


@pytest.fixture(scope="module")
def table():
    return pj.MTPATable.from_model(MAG, DRIVE.k_tau, DRIVE.i_max)


def _brute_force_mtpa(amp, sign):
    """The MTPA current at amplitude `amp` (A) by a dense numpy search over the angle
    advance (20001 angles on [0, pi/2], refined by the vertex of the parabola through the
    best three), on the map's flux: `(i_dq, torque)`."""
    g = np.linspace(0.0, 0.5 * np.pi, 20001)
    i = np.stack([-amp * np.sin(g), sign * amp * np.cos(g)], -1)
    psi = np.asarray(MAG.flux_dq(i))
    t = sign * K * (psi[:, 0] * i[:, 1] - psi[:, 1] * i[:, 0])
    j = int(np.argmax(t))
    y0, y1, y2 = t[j - 1], t[j], t[j + 1]
    gs = g[j] + 0.5 * (g[1] - g[0]) * (y0 - y2) / (y0 - 2.0 * y1 + y2)
    i_bf = np.array([-amp * np.sin(gs), sign * amp * np.cos(gs)])
    psi = np.asarray(MAG.flux_dq(i_bf))
    return i_bf, K * (psi[0] * i_bf[1] - psi[1] * i_bf[0])


def test_mtpa_on_the_map_against_a_brute_force_search(table):
    refs = pj.CurrentRefs("mtpa", 0.0, I_MAX, mtpa=table)
    for sign in (1.0, -1.0):
        for amp in (0.7, 2.5, 5.0, 8.3, 10.2):
            i_bf, tau = _brute_force_mtpa(amp, sign)
            i = np.asarray(refs(jnp.asarray(tau), MOTOR, DRIVE.k_tau))
            # the table's linear interpolation between amplitudes 0.083 A apart: measured
            # at most 3.5e-5 A from the brute force (whose own error is ~1e-9 A)
            np.testing.assert_allclose(i, i_bf, rtol=0, atol=1e-4)
            # the torque is the reference's (one Newton step), at an amplitude no larger
            # than the brute force's beyond the interpolation's second-order excess
            psi = np.asarray(MAG.flux_dq(i))
            assert abs(K * (psi[0] * i[1] - psi[1] * i[0]) - tau) < 1e-9 * abs(tau)
            assert np.hypot(*i) <= amp * (1 + 1e-7)
    # the saturated MTPA differs from the constants' (the test can tell them apart)
    constants = pj.PMSMParams(R_s=MOTOR.R_s, L_d=MOTOR.L_d, L_q=MOTOR.L_q,
                              psi_f=MOTOR.psi_f, n_p=MOTOR.n_p)
    i_const = np.asarray(pj.CurrentRefs("mtpa", 0.0, I_MAX)(jnp.asarray(tau), constants,
                                                            DRIVE.k_tau))
    assert np.max(np.abs(i_const - i_bf)) > 0.1


def test_id_const_gives_the_torque_of_the_map():
    for i_d in (0.0, -3.0):
        refs = pj.CurrentRefs("id_const", i_d, I_MAX)
        # up to the rated torque: below the current limit (1.09 rated at i_d = 0)
        tau = jnp.linspace(-1.0, 1.0, 9) * float(DRIVE.tau_rated)
        i = np.asarray(refs(tau, MOTOR, DRIVE.k_tau))
        assert np.all(i[:, 0] == i_d)
        psi = np.asarray(MAG.flux_dq(i))
        t = K * (psi[:, 0] * i[:, 1] - psi[:, 1] * i[:, 0])
        # NEWTON_STEPS = 2 from the constants' guess: measured 3.5e-7 of the rated torque
        # (the constants' own q-current misses the map's torque by up to 8 %)
        np.testing.assert_allclose(t, np.asarray(tau), rtol=0,
                                   atol=1e-6 * float(DRIVE.tau_rated))


def test_a_map_of_constant_inductances_gives_mtpa_i_d():
    m = pj.preset("morawiec_ipm3k5").motor
    g_d, g_q = np.linspace(-2 * I_MAX, 0.5 * I_MAX, 26), np.linspace(-2 * I_MAX, 2 * I_MAX, 41)
    dd, qq = np.meshgrid(g_d, g_q, indexing="ij")
    flux_map = pj.FluxMap(g_d, g_q, m.psi_f + m.L_d * dd, m.L_q * qq)
    motor = pj.PMSMParams(R_s=m.R_s, L_d=m.L_d, L_q=m.L_q, psi_f=m.psi_f, n_p=m.n_p,
                          magnetic=flux_map)
    refs = pj.CurrentRefs("mtpa", 0.0, I_MAX,
                          mtpa=pj.MTPATable.from_model(flux_map, DRIVE.k_tau, I_MAX))
    tau = jnp.linspace(-0.95, 0.95, 15) * K * float(m.psi_f) * I_MAX
    i = np.asarray(refs(tau, motor, DRIVE.k_tau))
    # the closed form on the map's q-current: the linear interpolation between table
    # amplitudes 0.083 A apart, largest near zero torque where i_d ~ i_q^2: measured 6.7e-5 A
    np.testing.assert_allclose(i[:, 0], np.asarray(pj.mtpa_i_d(i[:, 1], m)), rtol=0,
                               atol=2e-4)
    # and today's constant-inductance references (Newton on the closed form)
    np.testing.assert_allclose(i, np.asarray(pj.CurrentRefs("mtpa", 0.0, I_MAX)(
        tau, m, DRIVE.k_tau)), rtol=0, atol=1e-4)


def test_current_controller_gains_are_alpha_c_times_the_incremental_inductance():
    alpha_c = 2 * math.pi * 500.0
    cc = pj.CurrentController(motor=MOTOR, alpha_c=alpha_c, u_max=1e6)
    h = 1e-4
    for i in ([0.0, 0.0], [-3.0, 7.0], [-8.0, -5.0], [1.0, 10.0]):
        i = np.asarray(i)
        fd = np.stack([(np.asarray(MAG.flux_dq(i + h * e)) - np.asarray(MAG.flux_dq(
            i - h * e))) / (2 * h) for e in np.eye(2)], -1)  # d psi / d i, columns d, q
        Kp, Ki = cc.gains(jnp.asarray(i))
        # central differences: O(h^2) and rounding, measured below 1e-9 of the largest
        np.testing.assert_allclose(np.asarray(Kp), alpha_c * fd, rtol=0,
                                   atol=1e-8 * alpha_c * np.abs(fd).max())
        assert float(Ki) == pytest.approx(alpha_c * float(MOTOR.R_s))
        # the step uses them: u = K_p e + w J psi(i) from a zero integrator
        e, w = np.array([0.3, -0.2]), 150.0
        _, u = cc.step(cc.init(), jnp.asarray(i + e), jnp.asarray(i), w, 1e-4)
        psi = np.asarray(MAG.flux_dq(i))
        np.testing.assert_allclose(np.asarray(u), alpha_c * fd @ e + w * np.array(
            [-psi[1], psi[0]]), rtol=0, atol=1e-8 * np.abs(u).max())
    # the constants' controller: diag(alpha_c L_d, alpha_c L_q) at every current
    m = pj.preset("morawiec_ipm3k5").motor
    Kp, _ = pj.CurrentController(motor=m, alpha_c=alpha_c, u_max=1e6).gains(
        jnp.zeros((3, 2)))
    np.testing.assert_array_equal(np.asarray(Kp), np.broadcast_to(
        alpha_c * np.diag([m.L_d, m.L_q]), (3, 2, 2)))


def test_use_map_false_is_the_constant_controller():
    const = pj.preset("morawiec_ipm3k5")
    a = pj.FOC.from_drive(DRIVE, strategy="mtpa", use_map=False)
    b = pj.FOC.from_drive(const, strategy="mtpa")
    assert a.current.motor.magnetic is None and a.refs.mtpa is None
    assert pj.FOC.from_drive(DRIVE, strategy="mtpa").refs.mtpa is not None
    args = (jnp.asarray([0.4, 5.0]), 200.0, 210.0, 1e-4)
    for x, y in zip(jax.tree.leaves(a.step(a.init(), *args)),
                    jax.tree.leaves(b.step(b.init(), *args))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="needs `mtpa=MTPATable"):
        pj.CurrentRefs("mtpa", 0.0, I_MAX)(jnp.asarray(1.0), MOTOR, DRIVE.k_tau)


@pytest.fixture(scope="module")
def closed_loop():
    """Sensored speed control with MTPA and field weakening on the map (0.4 s, T_s = 125
    us): 0.5 p.u. speed at 0.8 p.u. load, and 1.5 p.u. speed at 0.4 p.u. load, where the
    MTPA current needs more than the inverter's voltage (measured: without field
    weakening the voltage saturates and the drive falls to 1.25 p.u.)."""
    foc = pj.FOC.from_drive(DRIVE, strategy="mtpa_fw", alpha_s=2 * math.pi * 15.0)
    speed, load = np.array([0.5, 1.5]), np.array([0.8, 0.4])

    def one(w, tl):
        sc = pj.Scenario(t_end=0.4, w_m_ref=pj.Profile.constant(w),
                         tau_L=pj.Profile.constant(tl))
        return pj.simulate(DRIVE, foc, pj.SensoredObserver(), sc, T_s=125e-6, w_m0=w,
                           throw=False)

    tr = jax.jit(jax.vmap(one))(jnp.asarray(speed * float(DRIVE.w_rated)),
                                jnp.asarray(load * float(DRIVE.tau_rated)))
    return foc, speed, load, jax.tree.map(np.asarray, tr)


def test_closed_loop_reaches_the_torque_on_the_map(closed_loop):
    foc, speed, load, tr = closed_loop
    last = slice(-800, None)  # the last 0.1 s
    tau_L = load[0] * float(DRIVE.tau_rated)
    assert bool(tr.ok[0])
    assert abs(np.mean(tr.w_m[0, last]) / (speed[0] * float(DRIVE.w_rated)) - 1) < 1e-4
    # B = 0: the mean torque is the load plus the rotor's acceleration, measured 5e-5 of
    # the load over the window
    assert abs(np.mean(tr.tau_M[0, last]) - tau_L) < 2e-4 * tau_L
    # the map's torque of the reference is the plant's (with the constants' references
    # it is 6 % off at this load); measured below 1e-7 of the load
    assert abs(np.mean(tr.tau_M[0, last] - tr.tau_ref[0, last])) < 1e-5 * tau_L


def test_closed_loop_field_weakening_keeps_the_voltage_limit(closed_loop):
    foc, speed, load, tr = closed_loop
    last = slice(-800, None)
    u_lim = float(DRIVE.inverter.u_lim)
    w = speed[1] * float(DRIVE.w_rated)
    assert bool(tr.ok[1])
    assert abs(np.mean(tr.w_m[1, last]) / w - 1) < 1e-4  # the speed is held
    u = np.hypot(tr.u_dq[1, last, 0], tr.u_dq[1, last, 1])
    # the steady flux uses u_margin = 0.9 of the limit, the resistive drop adds (measured
    # 0.9115 u_lim): the voltage stays clear of the limit and the current follows
    assert u.max() < 0.93 * u_lim
    assert np.abs(tr.i_dq[1, last] - tr.i_ref[1, last]).max() < 1e-4
    # the reference was weakened: the MTPA current of the same torque reference would
    # need more flux than the limit allows
    i_ref = tr.i_ref[1, -1]
    psi = np.asarray(MAG.flux_dq(i_ref))
    assert w * np.hypot(*psi) <= 0.9 * u_lim * (1 + 1e-9)
    i_mtpa = np.asarray(pj.CurrentRefs("mtpa", 0.0, I_MAX, mtpa=foc.refs.mtpa)(
        jnp.asarray(tr.tau_ref[1, -1]), MOTOR, DRIVE.k_tau))
    assert w * np.hypot(*np.asarray(MAG.flux_dq(i_mtpa))) > 1.05 * 0.9 * u_lim
    assert i_ref[0] < i_mtpa[0] - 1.0


def test_float32_saturated_run_is_float32_and_finite():
    """A sensorless (ESO) run with the map in the plant and the controller, cast to float32
    (`pj.astype`), against the same run in float64."""
    w = 0.5 * float(DRIVE.w_rated)

    def run(dtype):
        cast = (lambda t: t) if dtype == jnp.float64 else (lambda t: pj.astype(t, dtype))
        sc = pj.Scenario(t_end=0.05, w_m_ref=cast(pj.Profile.constant(w)),
                         tau_L=cast(pj.Profile.constant(0.5 * float(DRIVE.tau_rated))))
        return pj.simulate(cast(DRIVE), cast(pj.FOC.from_drive(DRIVE, strategy="mtpa_fw")),
                           cast(pj.ESOObserver.from_drive(DRIVE)), sc, T_s=125e-6,
                           w_m0=w, throw=False)

    tr, ref = run(jnp.float32), run(jnp.float64)
    assert tr.i_dq.dtype == jnp.float32 and tr.tau_M.dtype == jnp.float32
    assert bool(tr.ok) and np.all(np.isfinite(np.asarray(tr.i_dq)))
    # float32 rounding only: measured 2e-5 of the speed and 2e-4 A apart
    np.testing.assert_allclose(np.asarray(tr.w_m), np.asarray(ref.w_m), rtol=0,
                               atol=1e-3 * w)
    np.testing.assert_allclose(np.asarray(tr.i_dq), np.asarray(ref.i_dq), rtol=0,
                               atol=1e-2)
