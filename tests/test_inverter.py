"""Inverter non-linearity: the dead-time error model, the plant that receives it, the
observer-voltage compensation in simulate and replay, and the static angle error it causes
(analysis against simulation)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

import pmsmjax as pj
from pmsmjax.analysis import dead_time_angle_error, dead_time_resistance
from pmsmjax.observers import make_observer


DRIVE = pj.preset("zhang750")
U_DT, I_DT = 3.0, 0.1


def test_phase_errors_map_through_clarke():
    """The alpha-beta error equals the Clarke transform of the three phase errors computed
    from the phase currents (an independent route through `inv_clarke`/`clarke`)."""
    rng = np.random.default_rng(0)
    i_ab = rng.normal(scale=0.3, size=(50, 2))
    du_a, du_b = pj.dead_time_error_ab(U_DT, I_DT, i_ab[:, 0], i_ab[:, 1])
    i_abc = np.asarray(pj.inv_clarke(i_ab))
    ref = np.asarray(pj.clarke(U_DT * np.tanh(i_abc / I_DT)))
    np.testing.assert_allclose(np.stack([du_a, du_b], -1), ref, rtol=1e-13, atol=1e-13)


def test_limits_of_the_smooth_model():
    # small currents: an apparent resistance u_dt / i_dt along the current
    i = np.array([1e-7, -2e-7])
    du = np.stack(pj.dead_time_error_ab(U_DT, I_DT, i[0], i[1]))
    np.testing.assert_allclose(du, U_DT / I_DT * i, rtol=1e-9)
    # large sinusoidal currents: the fundamental tends to the square wave's 4 u_dt / pi
    assert abs(pj.dead_time_fundamental(U_DT, I_DT, 1e4 * I_DT) - 4 * U_DT / math.pi) < 1e-3
    # and the fundamental is the Fourier coefficient of the alpha component of the error
    # over one electrical period, along the current (computed through the vector model)
    amp = 0.25
    phi = np.linspace(0.0, 2 * np.pi, 4001)[:-1]
    du_a, du_b = pj.dead_time_error_ab(U_DT, I_DT, amp * np.cos(phi), amp * np.sin(phi))
    along = np.asarray(du_a) * np.cos(phi) + np.asarray(du_b) * np.sin(phi)
    np.testing.assert_allclose(along.mean(), pj.dead_time_fundamental(U_DT, I_DT, amp),
                               rtol=1e-10)
    assert float(dead_time_resistance(U_DT, I_DT, 0.0)) == pytest.approx(U_DT / I_DT)


def test_locked_rotor_dc_steady_state():
    """A DC voltage along alpha at standstill: R_s i_a + du_alpha(i) = u, with phase
    currents (I, -I/2, -I/2), so du_alpha = (2/3) u_dt (tanh(I/i_dt) + tanh(I/(2 i_dt)));
    solved by root finding and compared with the plant's settled current."""
    d = pj.replace_params(DRIVE, u_dt=U_DT, i_dt=I_DT)
    R = float(d.motor.R_s)
    u = 5.0
    f = lambda I: R * I + (2 / 3) * U_DT * (np.tanh(I / I_DT) + np.tanh(I / (2 * I_DT))) - u
    I_ref = brentq(f, 0.0, u / R)
    n = 4000
    T_s = 1e-4
    tr = pj.run_plant(d, jnp.arange(n) * T_s, jnp.tile(jnp.array([u, 0.0]), (n, 1)),
                      w_m_imposed=jnp.zeros(n))
    np.testing.assert_allclose(np.asarray(tr.i_ab[-1]), [I_ref, 0.0], rtol=1e-9, atol=1e-9)
    # an ideal inverter would give u / R
    assert abs(I_ref - u / R) > 0.1 * u / R


def test_power_balance_counts_the_applied_voltage():
    d = pj.replace_params(DRIVE, u_dt=U_DT, i_dt=I_DT)
    plant = pj.PMSM(d.motor, d.mechanics, d.inverter)
    y = pj.PlantState(i_dq=jnp.array([0.3, 2.0]), theta=jnp.array(0.7), w_m=jnp.array(200.0))
    args = pj.PlantInput(u_ab=jnp.array([40.0, -25.0]), tau_L=jnp.array(0.5))
    p_in, p_cu, dW, p_mech = plant.power_balance(y, args)
    assert float(p_in) == pytest.approx(float(p_cu + dW + p_mech), rel=1e-12)
    p_ideal = pj.PMSM(d.motor, d.mechanics).power_balance(y, args)[0]
    assert abs(float(p_in - p_ideal)) > 1.0  # the error takes power off the windings


def _run(drive, obs, w, load, **kw):
    sc = pj.Scenario(t_end=0.5, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.constant(load * drive.tau_rated))
    return pj.simulate(drive, pj.FOC.from_drive(drive), obs, sc, T_s=2.5e-4, w_m0=w,
                       throw=False, **kw)


def test_compensation_analysis_and_replay():
    """zhang750 at 0.1 p.u. and half load with 3 V of dead time: the ESO handed the
    commanded voltage settles at the static error the equilibrium analysis predicts (an
    extra resistance F(|i|)/|i|); with the drive's compensation it stays within 2 deg of
    the ideal inverter's run; replaying the commanded-voltage recording with the inverter
    model reproduces the in-loop estimates."""
    d = pj.replace_params(DRIVE, u_dt=U_DT, i_dt=I_DT)
    obs = make_observer("eso", d)
    w = 0.1 * float(d.w_rated)
    ideal = _run(DRIVE, obs, w, 0.5)
    raw = _run(d, obs, w, 0.5, observer_u_dt=0.0)
    comp = _run(d, obs, w, 0.5)
    late = np.asarray(raw.t) > 0.3
    err = lambda tr: np.degrees(np.asarray(tr.theta_err))[late]  # noqa: E731
    i_hat = np.asarray(pj.park(raw.i_ab, raw.theta_hat))[late].mean(0)
    pred = math.degrees(float(dead_time_angle_error(obs, d.motor, float(
        np.asarray(raw.w_m)[late].mean()), i_hat, U_DT, I_DT)))
    assert abs(pred) > 10.0
    assert abs(err(raw).mean() - pred) < 0.05 * abs(pred) + 3 * err(raw).std()
    assert abs(err(comp).mean() - err(ideal).mean()) < 2.0
    th, _ = pj.replay(obs, comp, theta0=0.0, w0=w, inverter=d.inverter)
    np.testing.assert_allclose(np.asarray(th), np.asarray(comp.theta_hat), atol=1e-9)
    # the commanded voltages replayed as if applied: the uncompensated error
    th_raw, _ = pj.replay(obs, raw, theta0=0.0, w0=w)
    np.testing.assert_allclose(np.asarray(th_raw), np.asarray(raw.theta_hat), atol=1e-9)


def test_bad_inverter_values():
    with pytest.raises(ValueError, match=r"Inverter\(u_dt=...\).*>= 0"):
        pj.Inverter(u_dc=300.0, u_dt=-1.0)
    with pytest.raises(ValueError, match=r"Inverter\(i_dt=...\).*> 0"):
        pj.Inverter(u_dc=300.0, u_dt=1.0, i_dt=0.0)
    with pytest.raises(ValueError, match="replay\\(inverter=...\\)"):
        obs = make_observer("eso", DRIVE)
        pj.replay(obs, jnp.arange(3) * 1e-4, jnp.zeros((3, 2)), jnp.zeros((3, 2)),
                  inverter=3.0)
    dtp = pj.replace_params(pj.preset("li_dtp"), u_dt=1.0)
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(10.0))
    with pytest.raises(ValueError, match="observer_u_dt"):
        pj.simulate(dtp, pj.FOC.from_drive(dtp), pj.SensoredObserver(), sc)


def test_motor_file_round_trip():
    d = pj.replace_params(DRIVE, u_dt=2.5, i_dt=0.2)
    back = pj.parse_motor_file(pj.motor_file_text(d))
    assert float(back.inverter.u_dt) == 2.5 and float(back.inverter.i_dt) == 0.2
    assert pj.parse_motor_file(pj.motor_file_text(DRIVE)).inverter.u_dt is None


def test_closed_loop_gradient_with_respect_to_u_dt():
    """The smooth model keeps the closed loop differentiable in u_dt: reverse-mode gradient
    of the final angle error against central differences."""
    import jax

    obs = make_observer("eso", DRIVE)
    w = 0.2 * float(DRIVE.w_rated)
    sc = pj.Scenario(t_end=0.05, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.constant(0.5 * float(DRIVE.tau_rated)))

    def f(u):
        d = pj.replace_params(DRIVE, u_dt=u)
        return pj.simulate(d, pj.FOC.from_drive(d), obs, sc, T_s=2.5e-4, w_m0=w,
                           observer_u_dt=0.0).theta_err[-1]

    g = float(jax.grad(f)(3.0))
    h = 1e-4
    fd = float((f(3.0 + h) - f(3.0 - h)) / (2 * h))
    assert abs(g) > 1e-3
    assert g == pytest.approx(fd, rel=1e-6)
