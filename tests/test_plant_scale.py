"""`Scenario(plant_scale=...)`: time-varying factors on the plant's machine parameters.

What is checked, and against what:

- locked rotor (imposed zero speed, current control), with a step of R_s, a step of L_q
  and a ramp of L_d at known times: the sampled currents equal a NumPy recursion of the
  scaled R-L circuits per axis driven by the voltage the trajectory records,
  i_{k+1} = a_k i_k + (1 - a_k) u_k / R_k, with R_k, L_k the factors written out here
  (np.interp, held over each period) and a_k the exact exp(-T R_k/L_k) (and RK4's own
  amplification factor, for a rounding-level comparison). The state is the current, so
  a step of an inductance keeps the current continuous;
- the same run against the unscaled circuit differs by far (the factors act);
- constant factors on R_s and psi_f at an imposed speed give the same run as a drive
  built with the scaled parameters from the start (controller designed for the unscaled
  drive in both), and the recorded torque is 1.5 n_p (psi_f' i_q + (L_d - L_q) i_d i_q)
  with the scaled flux;
- a step of psi_f at an imposed speed: the currents equal a fine-step NumPy RK4
  integration of the textbook dq model (tests/helpers.py) with the scaled flux, driven by
  the recorded stationary-frame voltage.
"""

import math

import numpy as np

import pmsmjax as pj

from .helpers import dq_rhs, motor_numbers, tree_max_abs_diff


T_S = 125e-6
DRIVE = pj.preset("zhang750")
R, LD, LQ, PSI_F, N_P = motor_numbers(DRIVE.motor)
FOC = pj.FOC.from_drive(DRIVE, alpha_c=2 * math.pi * 500.0)

# event times half a sample before a sampling instant (no rounding question)
T_R, T_LQ, T_LD0, T_LD1 = 0.0105 - T_S / 2, 0.0205 - T_S / 2, 0.03, 0.035
T_END = 0.045


def _rk4_factor(z):
    """Amplification factor of classical RK4 for x' = -x/tau over z = h/tau."""
    return 1 - z + z ** 2 / 2 - z ** 3 / 6 + z ** 4 / 24


def _scales(t):
    """The factors at the instants `t`, written out independently of `Profile`."""
    k_r = np.where(t >= T_R, 1.6, 1.0)
    k_lq = np.where(t >= T_LQ, 0.5, 1.0)
    k_ld = np.interp(t, [T_LD0, T_LD1], [1.0, 1.4])
    return k_r, k_ld, k_lq


def _locked_rotor_run(scaled=True):
    plant_scale = {
        "R_s": pj.Profile.steps([T_R], [1.6], initial=1.0),
        "L_q": pj.Profile.steps([T_LQ], [0.5], initial=1.0),
        "L_d": pj.Profile.ramp(T_LD0, T_LD1, 1.0, 1.4),
    } if scaled else None
    sc = pj.Scenario(t_end=T_END,
                     i_d_ref=pj.Profile.steps([0.005, 0.025], [-2.0, -4.0]),
                     i_q_ref=pj.Profile.steps([0.002, 0.015, 0.032], [3.0, 5.0, 1.0]),
                     w_m_imposed=pj.Profile.constant(0.0), plant_scale=plant_scale)
    return pj.simulate(DRIVE, FOC, pj.SensoredObserver(), sc, T_s=T_S)


def _rl_reference(t, u, i0, k_r, k_ld, k_lq, exact=True):
    """Per axis at w = 0: the ZOH response of L_k di/dt = u_k - R_k i over each period."""
    out = np.zeros((len(t), 2))
    out[0] = i0
    for ax, (L0, k_l) in enumerate([(LD, k_ld), (LQ, k_lq)]):
        for k in range(len(t) - 1):
            Rk, Lk = R * k_r[k], L0 * k_l[k]
            z = T_S * Rk / Lk
            a = math.exp(-z) if exact else _rk4_factor(z)
            out[k + 1, ax] = a * out[k, ax] + (1 - a) * u[k, ax] / Rk
    return out


def test_locked_rotor_parameter_steps_against_the_scaled_rl_circuit():
    tr = _locked_rotor_run()
    assert bool(tr.ok)
    t = np.asarray(tr.t)
    i = np.asarray(tr.i_dq)
    u = np.asarray(tr.u_dq)  # theta = 0: the voltage the windings received
    np.testing.assert_array_equal(np.asarray(tr.theta), 0.0)
    k_r, k_ld, k_lq = _scales(t)
    assert k_r[-1] == 1.6 and k_lq[-1] == 0.5 and k_ld[-1] == 1.4
    # RK4's own factor: the same recursion to rounding.
    ref_rk4 = _rl_reference(t, u, i[0], k_r, k_ld, k_lq, exact=False)
    np.testing.assert_allclose(i, ref_rk4, rtol=0, atol=1e-11)
    # The exact ZOH response. Both recursions are linear, so their difference obeys
    # e_{k+1} = a_k e_k + (a_rk4 - a_k)(i_k - u_k/R_k) exactly; |a_rk4 - a| ~ z^5/120
    # (z = T R/L <= 0.12 here, R x 1.6 and L_q x 0.5) and |i - u/R| reaches tens of
    # amperes when a reference steps. The bound is that recursion in absolute values.
    ref = _rl_reference(t, u, i[0], k_r, k_ld, k_lq)
    bound = np.zeros((len(t), 2))
    for k in range(len(t) - 1):
        for ax, L0, k_l in ((0, LD, k_ld), (1, LQ, k_lq)):
            z = T_S * R * k_r[k] / (L0 * k_l[k])
            bound[k + 1, ax] = math.exp(-z) * bound[k, ax] + abs(
                _rk4_factor(z) - math.exp(-z)) * abs(i[k, ax] - u[k, ax] / (R * k_r[k]))
    assert bound.max() < 1e-4  # the solver's error is small against the effects below
    assert np.all(np.abs(i - ref) <= 1.01 * bound + 1e-12)
    # The factors do act: the unscaled circuit with the same voltages is far off.
    ones = np.ones_like(t)
    unscaled = _rl_reference(t, u, i[0], ones, ones, ones)
    assert np.abs(unscaled - i).max() > 0.5
    # ... and the events are where the scenario puts them: before the first one the
    # scaled and unscaled circuits agree.
    before = t < T_R
    np.testing.assert_allclose(i[before], unscaled[before], rtol=0, atol=3e-6)


def test_constant_scale_equals_a_drive_built_scaled():
    """A constant factor on R_s and psi_f from t = 0 is a drive with those parameters;
    the torque the run records uses the scaled flux."""
    kw = dict(t_end=0.03, i_d_ref=pj.Profile.steps([0.002], [-1.0]),
              i_q_ref=pj.Profile.steps([0.001, 0.015], [4.0, -2.0]),
              w_m_imposed=pj.Profile.constant(300.0))
    sc = pj.Scenario(**kw, plant_scale={"R_s": pj.Profile.constant(1.3),
                                        "psi_f": pj.Profile.constant(0.9)})
    a = pj.simulate(DRIVE, FOC, pj.SensoredObserver(), sc, T_s=T_S)
    built = pj.replace_params(DRIVE, R_s=1.3 * R, psi_f=0.9 * PSI_F)
    b = pj.simulate(built, FOC, pj.SensoredObserver(), pj.Scenario(**kw), T_s=T_S)
    # the same arithmetic up to the product R * 1.3 computed in two places
    assert tree_max_abs_diff(a, b) < 1e-9
    i = np.asarray(a.i_dq)
    tau = 1.5 * N_P * (0.9 * PSI_F * i[:, 1] + (LD - LQ) * i[:, 0] * i[:, 1])
    np.testing.assert_allclose(np.asarray(a.tau_M), tau, rtol=1e-12, atol=1e-12)
    # against the unscaled drive, the torque differs by the flux factor
    c = pj.simulate(DRIVE, FOC, pj.SensoredObserver(), pj.Scenario(**kw), T_s=T_S)
    assert np.abs(np.asarray(c.i_dq) - i).max() > 0.05


def test_flux_step_at_speed_against_the_dq_model():
    """psi_f x 0.8 at 12 ms at an imposed 300 rad/s: the back-EMF drops by 3.4 V and the
    currents follow the scaled model. Reference: helpers.dq_rhs (written out by hand),
    RK4 with 16 steps per period on the recorded u_ab, the flux switched at the same
    sample; the simulation's single RK4 step per period differs from it by the local
    error (|lambda| T)^5/120 with |lambda| T = hypot(R/L, w) T = 0.05 (3e-9 relative per
    step), summed over the transient: allow 1e-6 of the 5 A scale."""
    w, t_step = 300.0, 0.012 - T_S / 2
    sc = pj.Scenario(t_end=0.025, i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.steps([0.002], [5.0]),
                     w_m_imposed=pj.Profile.constant(w),
                     plant_scale={"psi_f": pj.Profile.steps([t_step], [0.8], initial=1.0)})
    tr = pj.simulate(DRIVE, FOC, pj.SensoredObserver(), sc, T_s=T_S)
    assert bool(tr.ok)
    t = np.asarray(tr.t)
    u_ab = np.asarray(tr.u_ab)
    i = np.asarray(tr.i_dq)
    J, B = float(DRIVE.mechanics.J), float(DRIVE.mechanics.B)
    weak = pj.replace_params(DRIVE, psi_f=0.8 * PSI_F).motor
    n_sub = 16
    h = T_S / n_sub
    x = np.array([0.0, 0.0, 0.0, w])
    ref = [x[:2].copy()]
    for k in range(len(t) - 1):
        motor = weak if t[k] >= t_step else DRIVE.motor
        for _ in range(n_sub):
            k1 = dq_rhs(motor, J, B, x, u_ab[k], 0.0, free=False)
            k2 = dq_rhs(motor, J, B, x + h / 2 * k1, u_ab[k], 0.0, free=False)
            k3 = dq_rhs(motor, J, B, x + h / 2 * k2, u_ab[k], 0.0, free=False)
            k4 = dq_rhs(motor, J, B, x + h * k3, u_ab[k], 0.0, free=False)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        ref.append(x[:2].copy())
    ref = np.asarray(ref)
    np.testing.assert_allclose(i, ref, rtol=0, atol=1e-6 * 5.0)
    np.testing.assert_allclose(np.asarray(tr.theta), np.angle(np.exp(1j * w * t)),
                               rtol=0, atol=1e-9)
    # the step is felt: the decoupling (unscaled model) now over-compensates the EMF by
    # 0.2 w psi_f = 3.4 V on q, which the current loop has to remove
    k = np.searchsorted(t, t_step)
    assert np.abs(i[k:k + 40, 1] - 5.0).max() > 0.1
