"""The voltage limit and the anti-windup of the FOC (`pmsmjax._control`).

What is checked, and against what:

- the voltage the controller applies never leaves the inverter's circle
  |u| <= u_max (`Inverter.u_lim`), in a locked-rotor run and in a rotating one, and it
  reaches that circle when the reference asks for more (the check is not vacuous);
- a locked-rotor current step the inverter cannot deliver: while the controller is
  saturated the machine sees the constant voltage u_max on the q axis, so the current is
  the closed-form R-L step response i(t) = (u_max/R)(1 - exp(-t R/L));
- anti-windup by back-calculation: with a constant error beyond the limit, the
  integrator obeys x_{k+1} = x_k + T (R/L) (u_max - x_k) (the module's update law with
  u = K_p e + x and u_lim = u_max), i.e. the closed form
  x_k = u_max (1 - (1 - T R/L)^k): it converges to u_max instead of growing like
  k T K_i e. Checked on the controller directly, and in the loop through what the current
  does after the reference drops back to a feasible value: the response is that of the
  unsaturated linear loop (a plain NumPy recursion written here) started from the
  closed-form integrator value and current;
- in two dimensions (equal inductances, standstill) the integrator stays inside the
  circle |x| <= u_max (each update is a convex combination of x and a point on the
  circle) and converges to u_max along the error;
- the speed controller's torque limit and its back-calculation in the same way:
  x_k = tau_max (1 - (1 - T alpha_s / 2)^k).
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj

from .helpers import motor_numbers


T_S = 125e-6
U_MAX = 5.0  # V: low on purpose, so that a current of a few amperes needs more
BASE = pj.preset("zhang750")
DRIVE = eqx.tree_at(lambda d: d.inverter, BASE, pj.Inverter(u_dc=311.0, u_max=U_MAX))
R, LD, LQ, PSI_F, N_P = motor_numbers(DRIVE.motor)
ALPHA_C = 2 * math.pi * 500.0
KP_Q, KI = ALPHA_C * LQ, ALPHA_C * R
I_SAT = U_MAX / R  # the largest current u_max can hold at standstill (6.41 A)

I_STEP = 10.0  # A: asks for R * 10 = 7.8 V at standstill, more during the transient
# After the saturated phase the reference drops to I_SAT - 1 A: with the integrator at
# u_max (x = R i, a consistent steady state) the first voltage is u_max - K_p * 1 A
# = -3.4 V, inside the circle, so the recovery is linear from its first sample.
I_BACK = I_SAT - 1.0
K_DROP = 240  # the drop acts at sample 240 (t = 30 ms, 8.8 time constants L/R)
T_DROP = (K_DROP - 0.5) * T_S  # half a sample before the instant: no rounding question
T_END = 0.06


def _rk4_factor(z):
    """Amplification factor of classical RK4 for x' = -x/tau over z = h/tau."""
    return 1 - z + z ** 2 / 2 - z ** 3 / 6 + z ** 4 / 24


def _locked_rotor_run():
    foc = pj.FOC.from_drive(DRIVE, alpha_c=ALPHA_C)
    sc = pj.Scenario(t_end=T_END, i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.steps([T_DROP], [I_BACK], initial=I_STEP),
                     w_m_imposed=pj.Profile.constant(0.0))
    return pj.simulate(DRIVE, foc, pj.SensoredObserver(), sc, T_s=T_S)


def test_locked_rotor_step_beyond_the_limit_and_recovery():
    tr = _locked_rotor_run()
    assert bool(tr.ok)
    t = np.asarray(tr.t)
    u = np.asarray(tr.u_dq)
    i = np.asarray(tr.i_dq)
    k1 = int(np.argmax(np.asarray(tr.i_ref)[:, 1] < I_STEP))
    assert k1 == K_DROP

    # The circle, at every sample (rounding only).
    assert np.all(np.hypot(u[:, 0], u[:, 1]) <= U_MAX * (1 + 1e-12))

    # Saturated phase: the unlimited q voltage K_p (10 A - i) + x >= K_p * 3.6 A = 30 V is
    # far outside the circle, the d axis has no error and no coupling (w = 0): the
    # machine sees exactly (0, u_max).
    np.testing.assert_allclose(u[:K_DROP], np.tile([0.0, U_MAX], (K_DROP, 1)), rtol=0,
                               atol=1e-12 * U_MAX)
    np.testing.assert_array_equal(i[:, 0], 0.0)
    # ... so the current is the R-L step response. RK4 (one step per period, z = RT/L
    # = 0.036) has the amplification factor exp(-z) + O(z^5/120): the error of a^k is
    # at most max_k k e^{-kz} z^5/120 = z^4/(120 e) = 5e-9 relative to u_max/R.
    i_rl = I_SAT * (1 - np.exp(-t[:K_DROP + 1] * R / LQ))
    np.testing.assert_allclose(i[:K_DROP + 1, 1], i_rl, rtol=0, atol=1e-7 * I_SAT)

    # Anti-windup: the integrator at the drop, in closed form (see the module docstring).
    x0 = U_MAX * (1 - (1 - T_S * R / LQ) ** K_DROP)
    assert U_MAX - x0 < 1e-3 * U_MAX  # it has converged to the limit, not beyond
    # The recovery from (i_0, x_0): the unsaturated PI and the ZOH plant (RK4 factor, as
    # the simulation's solver; its difference from exp(-z) is the 5e-9 above).
    a = _rk4_factor(R * T_S / LQ)
    i_ref, x, u_ref = [i[K_DROP, 1]], x0, []
    for _ in range(K_DROP, len(t) - 1):
        e = I_BACK - i_ref[-1]
        u_k = KP_Q * e + x
        u_ref.append(u_k)
        x += T_S * KI * e
        i_ref.append(a * i_ref[-1] + (1 - a) * u_k / R)
    u_ref = np.asarray(u_ref)
    assert np.all(np.abs(u_ref) < U_MAX)  # the reference itself never saturates
    # i_0 enters from the simulation (checked above to 1e-7), x_0 from the closed form:
    # a wrong integrator value would show as an error of order (x_0 - x)/R.
    np.testing.assert_allclose(i[K_DROP:, 1], i_ref, rtol=0, atol=1e-6 * I_SAT)
    np.testing.assert_allclose(u[K_DROP:-1, 1], u_ref, rtol=0, atol=1e-6 * U_MAX)
    # First order: no undershoot below the new reference worth speaking of, settled.
    assert i[K_DROP:, 1].min() > I_BACK - 0.01 * (I_SAT - I_BACK)
    assert abs(i[-1, 1] - I_BACK) < 1e-3

    # Without anti-windup the integrator would hold sum T K_i e_k (> 300 V here) and the
    # current would stay at I_SAT for about 0.1 s after the drop: the check above separates
    # the two by far.
    x_windup = T_S * KI * np.sum(I_STEP - i[:K_DROP, 1])
    assert x_windup > 50 * U_MAX


def test_limit_while_rotating():
    """At an imposed speed with a current vector it cannot reach (i_d = -3 A, i_q = 10 A
    at 50 rad/s: back-EMF 2.8 V, R|i| = 8.1 V), the voltage stays on or inside the
    circle and reaches it; the d axis and the coupling terms take part."""
    foc = pj.FOC.from_drive(DRIVE, alpha_c=ALPHA_C)
    sc = pj.Scenario(t_end=0.02, i_d_ref=pj.Profile.constant(-3.0),
                     i_q_ref=pj.Profile.constant(10.0),
                     w_m_imposed=pj.Profile.constant(50.0))
    tr = pj.simulate(DRIVE, foc, pj.SensoredObserver(), sc, T_s=T_S)
    assert bool(tr.ok)
    for v in (np.asarray(tr.u_dq), np.asarray(tr.u_ab)):
        n = np.hypot(v[:, 0], v[:, 1])
        assert np.all(n <= U_MAX * (1 + 1e-12))
        assert n.max() >= U_MAX * (1 - 1e-12)  # saturated: the limit is reached
        assert np.mean(n >= U_MAX * (1 - 1e-9)) > 0.9  # and it stays there
    # the voltage is not along q only: the limit scales the vector, not one axis
    assert np.abs(np.asarray(tr.u_dq)[:, 0]).max() > 0.1 * U_MAX


def test_current_controller_integrator_closed_form():
    """The controller alone, with a measured current the machine cannot follow (held at
    zero): u stays at u_max and x_k = u_max (1 - (1 - T R/L)^k) exactly."""
    cc = pj.CurrentController(motor=DRIVE.motor, alpha_c=ALPHA_C, u_max=U_MAX)
    step = eqx.filter_jit(cc.step)
    s = cc.init()
    n = 400
    x_q, u_q = [], []
    for _ in range(n):
        s, u = step(s, jnp.array([0.0, I_STEP]), jnp.zeros(2), 0.0, T_S)
        x_q.append(float(s.x_I[1]))
        u_q.append(np.asarray(u))
        assert float(s.x_I[0]) == 0.0
    u_q = np.asarray(u_q)
    np.testing.assert_allclose(u_q, np.tile([0.0, U_MAX], (n, 1)), rtol=0, atol=1e-12)
    k = np.arange(1, n + 1)
    closed = U_MAX * (1 - (1 - T_S * R / LQ) ** k)
    np.testing.assert_allclose(x_q, closed, rtol=1e-12, atol=1e-12 * U_MAX)
    assert max(x_q) <= U_MAX  # never beyond the voltage that produces u_max
    assert n * T_S * KI * I_STEP > 100 * U_MAX  # what a plain integrator would hold


def test_integrator_stays_in_the_circle_in_two_dimensions():
    """Equal model inductances, standstill, a constant error in a general direction: the
    update x <- x + T (R/L) (u_lim - x) is a convex combination of x and a point of the
    circle (T R/L < 1), so |x| <= u_max at every step, and the fixed point is u_max along
    the error (u_lim = x there, so x is parallel to u = K_p e + x)."""
    m = pj.PMSMParams(R_s=R, L_d=LQ, L_q=LQ, psi_f=PSI_F, n_p=N_P)
    cc = pj.CurrentController(motor=m, alpha_c=ALPHA_C, u_max=U_MAX)
    step = eqx.filter_jit(cc.step)
    e = np.array([-4.0, 7.0])
    s = cc.init()
    norms = []
    for _ in range(1500):
        s, u = step(s, jnp.asarray(e), jnp.zeros(2), 0.0, T_S)
        assert float(jnp.hypot(u[0], u[1])) <= U_MAX * (1 + 1e-12)
        norms.append(float(jnp.hypot(s.x_I[0], s.x_I[1])))
    assert max(norms) <= U_MAX * (1 + 1e-12)
    # (1 - T R/L)^1500 = 2e-24: converged to rounding
    np.testing.assert_allclose(np.asarray(s.x_I), U_MAX * e / np.linalg.norm(e),
                               rtol=0, atol=1e-9 * U_MAX)


def test_speed_controller_torque_limit_and_back_calculation():
    """tau = clip(k_p e + x, +-tau_max); with a constant error beyond the limit the
    integrator obeys x_{k+1} = x_k + T (k_i/k_p) (tau_max - x_k), k_i/k_p = alpha_s/2."""
    alpha_s, tau_max, j_np = 2 * math.pi * 5.0, 4.8, 1.5e-3 / 5
    sc = pj.SpeedController(J_over_np=j_np, alpha_s=alpha_s, tau_max=tau_max)
    step = eqx.filter_jit(sc.step)
    kp = 2 * alpha_s * j_np
    e = 1.5 * tau_max / kp  # k_p e alone is 1.5 tau_max
    for sign in (1.0, -1.0):
        s = sc.init()
        xs = []
        for _ in range(200):
            s, tau = step(s, sign * e, 0.0, T_S)
            assert float(tau) == sign * tau_max
            xs.append(float(s.x_I))
        k = np.arange(1, 201)
        closed = sign * tau_max * (1 - (1 - T_S * alpha_s / 2) ** k)
        np.testing.assert_allclose(xs, closed, rtol=1e-12, atol=1e-15)
