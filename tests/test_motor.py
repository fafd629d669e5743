"""Physics of the PMSM plant against closed-form results and independent integrations.

References used here (none taken from the library's own output):
- steady-state dq voltages and the locked-rotor R-L step response (closed form);
- torque by virtual work: tau = k n_p dW'/dtheta at constant stationary-frame currents,
  W' the co-energy of the stationary-frame model, differentiated with jax.grad;
- the power / energy balance of the stator circuit;
- scipy DOP853 integration of the textbook dq equations written out in `helpers.py`;
- the x-y subspace of a dual three-phase machine as an R-L circuit driven by the back-EMF
  harmonics (phasor solution), with the six-phase PM flux mapped through `pj.vsd`.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import pmsmjax as pj

from .helpers import dq_rhs, motor_numbers, rot, simpson, steady_u_dq, with_harmonics


THREE_PHASE = ["zhang750", "stumper_mt5", "morawiec_ipm3k5"]


def state(i_dq, theta, w_m, i_xy=None):
    return pj.PlantState(i_dq=jnp.asarray(i_dq, float), theta=jnp.asarray(theta, float),
                         w_m=jnp.asarray(w_m, float),
                         i_xy=None if i_xy is None else jnp.asarray(i_xy, float))


# --------------------------------------------------------------------------------------
# Steady state
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", THREE_PHASE)
def test_steady_state_vector_field(name):
    """With the steady-state voltage the dq current is an equilibrium, dtheta/dt = w."""
    drive = pj.preset(name)
    plant = pj.PMSM(drive.motor, drive.mechanics)
    R, Ld, Lq, psi_f, _ = motor_numbers(drive.motor)
    rng = np.random.default_rng(0)
    thetas = [0.0, 1.0, -2.5, 17.3]
    i_dq = np.repeat(rng.uniform(-1, 1, (15, 2)) * float(drive.i_max), len(thetas), 0)
    w = np.repeat(rng.uniform(-2, 2, 15) * float(drive.w_rated), len(thetas))
    theta = np.tile(thetas, 15)
    u_dq = np.stack([steady_u_dq(drive.motor, i, ww) for i, ww in zip(i_dq, w)])
    u_ab = np.einsum("kij,kj->ki", np.stack([rot(a) for a in theta]), u_dq)
    vf = jax.vmap(lambda y, u: plant.vector_field(0.0, y, pj.PlantInput(u_ab=u, tau_L=0.0)))
    dy = vf(state(i_dq, theta, w), jnp.asarray(u_ab))
    # Size of the individual terms of L di/dt (V / H): the cancellation must be exact to
    # rounding.
    scale = (np.abs(u_dq).max(-1) + R * np.abs(i_dq).max(-1)
             + np.abs(w) * (max(Ld, Lq) * np.abs(i_dq).max(-1) + psi_f)) / min(Ld, Lq)
    assert np.all(np.abs(np.asarray(dy.i_dq)) <= 1e-13 * scale[:, None])
    np.testing.assert_array_equal(np.asarray(dy.theta), w)


def _zoh_steady_run(drive, i_dq, w, T_s, N, advance):
    theta0 = 0.4
    u_dq = steady_u_dq(drive.motor, i_dq, w)
    t = np.arange(N) * T_s
    th = theta0 + w * t + (0.5 * w * T_s if advance else 0.0)
    u_ab = np.einsum("kij,j->ki", np.stack([rot(a) for a in th]), u_dq)
    tr = pj.run_plant(drive, t, u_ab, n_substeps=1, theta0=theta0, w_m0=w, i_dq0=i_dq,
                      w_m_imposed=np.full(N, w))
    return np.asarray(tr.i_dq), u_dq


@pytest.mark.parametrize("name", ["zhang750", "morawiec_ipm3k5"])
def test_steady_state_zoh_run(name):
    r"""Imposed speed, ZOH stationary voltage u_ab(t_k) = e^{(theta_k + w T/2) J} u_dq*.

    Over one hold interval the voltage seen in dq is e^{-phi J} u*, phi = w(tau - T/2)
    in [-wT/2, wT/2). Split e^{-phi J} - I = -phi J + O(phi^2):
    - the first-order part has zero mean; its running integral is at most w T^2 / 8 |u*|,
      so it gives a current ripple of at most ||L^-1|| w T^2 |u*| / 8;
    - the mean of (cos phi - 1) is -(wT)^2/24: a constant voltage error of at most
      (wT)^2/24 |u*|, which moves the current by ||Z^-1|| (wT)^2/24 |u*| in steady state,
      Z = [[R, -w L_q], [w L_d, R]]; the transient to it overshoots by at most
      ||e^{At}|| <= sqrt(L_max/L_min) (energy norm; i^T L i is non-increasing).
    The tolerance is the sum of both bounds with a factor 1.5 for the neglected
    O((wT)^3) terms. Without the half-sample advance the mean voltage error is
    (wT/2)|u*|: the same check must then fail by a wide margin.
    """
    drive = pj.preset(name)
    R, Ld, Lq, psi_f, _ = motor_numbers(drive.motor)
    w = float(drive.w_rated)
    i_dq = np.array([-0.3, 0.8]) * float(drive.i_max)
    T_s, N = 1e-6, 2000
    i_sim, u_dq = _zoh_steady_run(drive, i_dq, w, T_s, N, advance=True)
    u = np.linalg.norm(u_dq)
    Z = np.array([[R, -w * Lq], [w * Ld, R]])
    Zinv = np.linalg.norm(np.linalg.inv(Z), 2)
    ripple = w * T_s ** 2 / 8 * u / min(Ld, Lq)
    offset = (1 + math.sqrt(max(Ld, Lq) / min(Ld, Lq))) * Zinv * (w * T_s) ** 2 / 24 * u
    tol = 1.5 * (ripple + offset)
    err = np.linalg.norm(i_sim - i_dq, axis=-1).max()
    assert err < tol, (err, tol)
    # Sensitivity: without the advance the error is first order in wT and far larger.
    i_bad, _ = _zoh_steady_run(drive, i_dq, w, T_s, N, advance=False)
    assert np.linalg.norm(i_bad - i_dq, axis=-1).max() > 20 * tol


# --------------------------------------------------------------------------------------
# Locked rotor R-L step
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("axis", ["d", "q"])
@pytest.mark.parametrize("name, T_s", [("zhang750", 1e-5), ("morawiec_ipm3k5", 5e-5)])
def test_locked_rotor_step(name, T_s, axis):
    r"""w = 0, theta = 0: a voltage step U along alpha (beta) is a step on d (q):
    i(t) = U/R (1 - exp(-R t / L)).

    RK4 on x' = -a x + b is exact up to the amplification-factor error
    |R(z) - e^{-z}| ~ z^5/120 per step, z = a h; with h = T_s / 2 and a = R/L, z <= 1.6e-3
    and the global relative error is ~ N z^5 / 120 < 1e-13: the comparison is limited by
    rounding (tolerance 1e-11 of U/R). The run covers more than one time constant.
    """
    drive = pj.preset(name)
    R, Ld, Lq, _, _ = motor_numbers(drive.motor)
    L = Ld if axis == "d" else Lq
    U = 7.0
    N = 3000
    t = np.arange(N) * T_s
    u_ab = np.zeros((N, 2))
    u_ab[:, 0 if axis == "d" else 1] = U
    tr = pj.run_plant(drive, t, u_ab, n_substeps=2, theta0=0.0, w_m0=0.0,
                      w_m_imposed=np.zeros(N))
    i_ref = U / R * (1.0 - np.exp(-R * t / L))
    k, other = (0, 1) if axis == "d" else (1, 0)
    i_dq = np.asarray(tr.i_dq)
    np.testing.assert_allclose(i_dq[:, k], i_ref, rtol=0, atol=1e-11 * U / R)
    np.testing.assert_allclose(i_dq[:, other], 0.0, atol=1e-14 * U / R)
    np.testing.assert_allclose(np.asarray(tr.theta), 0.0, atol=0)
    # The stationary-frame current equals the dq current at theta = 0.
    np.testing.assert_allclose(np.asarray(tr.i_ab), i_dq, atol=1e-14 * U / R)
    assert t[-1] * R / L > 1.5 and (T_s / 2) * R / L < 2e-3


# --------------------------------------------------------------------------------------
# Torque and power balance
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", THREE_PHASE)
def test_torque_formula(name):
    drive = pj.preset(name)
    plant = pj.PMSM(drive.motor, drive.mechanics)
    R, Ld, Lq, psi_f, n_p = motor_numbers(drive.motor)
    rng = np.random.default_rng(1)
    for _ in range(20):
        i_dq = rng.uniform(-1, 1, 2) * float(drive.i_max)
        theta, w = rng.uniform(-10, 10), rng.uniform(-1, 1) * float(drive.w_rated)
        tau = float(plant.torque(state(i_dq, theta, w)))
        psi_d, psi_q = Ld * i_dq[0] + psi_f, Lq * i_dq[1]
        ref = 1.5 * n_p * (psi_d * i_dq[1] - psi_q * i_dq[0])
        assert tau == pytest.approx(ref, rel=1e-13, abs=1e-13 * float(drive.tau_rated))
        # The mechanical equation: J/n_p dw/dt = tau - B w / n_p - tau_L.
        tau_L = rng.uniform(-1, 1) * float(drive.tau_rated)
        dy = plant.vector_field(0.0, state(i_dq, theta, w),
                                pj.PlantInput(u_ab=jnp.zeros(2), tau_L=tau_L))
        J, B = float(drive.mechanics.J), float(drive.mechanics.B)
        assert float(dy.w_m) == pytest.approx(n_p * (ref - B * w / n_p - tau_L) / J,
                                              rel=1e-12)


ANG6 = np.deg2rad([0.0, 120.0, 240.0, 30.0, 150.0, 270.0])
ANG3 = ANG6[:3]


def _coenergy_torque(drive, y):
    r"""Torque by virtual work from an independent stationary-frame (phase) model.

    Phase k of a winding at electrical angle a_k links the PM flux
    psi_f cos(theta - a_k) + sum_h psi_f a_h/|h| cos(h theta + phi_h - h a_k)
    (signed order h: a spatial harmonic of order |h| seen by the winding), and the
    stator self-flux L_ab(theta) i_ab with L_ab = e^{theta J} diag(L_d, L_q) e^{-theta J}
    (x-y subspace: L_xy, no saliency). The co-energy in vector coordinates is
    W' = 1/2 i^T L_ab i + i . psi_pm,ab + 1/2 L_xy |i_xy|^2 + i_xy . psi_pm,xy and
    tau = k n_p dW'/dtheta at fixed stationary currents (k = 3/2 or 3: the power scaling
    of amplitude-invariant vectors). psi_pm,ab/xy are obtained with `pj.clarke` / `pj.vsd`
    from the phase fluxes. `y` holds a batch of states (leading axis).
    """
    dual = drive.dual
    m = drive.motor.ab if dual else drive.motor
    R, Ld, Lq, psi_f, n_p = motor_numbers(m)
    harm = m.harmonics
    ang = ANG6 if dual else ANG3

    def phase_flux(theta):
        psi = psi_f * jnp.cos(theta - ang)
        if harm is not None:
            for h, a, ph in zip(harm.order, np.asarray(harm.amplitude),
                                np.asarray(harm.phase)):
                psi = psi + psi_f * a / abs(h) * jnp.cos(h * theta + ph - h * ang)
        return psi

    def W(theta, i_ab, i_xy):
        c, s = jnp.cos(theta), jnp.sin(theta)
        Rm = jnp.array([[c, -s], [s, c]])
        L_ab = Rm @ jnp.diag(jnp.array([Ld, Lq])) @ Rm.T
        w = 0.5 * i_ab @ L_ab @ i_ab
        if dual:
            pab, pxy, _ = pj.vsd(phase_flux(theta))
            return w + i_ab @ pab + i_xy @ pxy
        return w + i_ab @ pj.clarke(phase_flux(theta))

    k = 3.0 if dual else 1.5
    i_ab = pj.inv_park(y.i_dq, y.theta)
    i_xy = y.i_xy if dual else jnp.zeros_like(i_ab)
    dW = jax.jit(jax.vmap(jax.grad(W)))(y.theta, i_ab, i_xy)
    return k * n_p * np.asarray(dW)


def _random_states(rng, drive, n, w_frac):
    i_max = float(drive.i_max)
    return state(rng.uniform(-1, 1, (n, 2)) * i_max, rng.uniform(-10, 10, n),
                 rng.uniform(-w_frac, w_frac, n) * float(drive.w_rated),
                 i_xy=rng.uniform(-0.3, 0.3, (n, 2)) * i_max if drive.dual else None)


def _drives_with_harmonics():
    z = with_harmonics(pj.preset("zhang750"), (-5, 7, -11, 13), (0.04, 0.03, 0.02, 0.01),
                       (0.3, -0.7, 1.1, 0.0))
    m = with_harmonics(pj.preset("morawiec_ipm3k5"), (-17, 19), (0.05, 0.04), (0.5, 0.2))
    dtp = pj.preset("li_dtp")
    # all routings: 5/7/17/19 -> x-y, 11/13 -> alpha-beta
    dtp2 = with_harmonics(dtp, (-5, 7, -11, 13, -17, 19), (0.03, 0.02, 0.015, 0.01, 0.01,
                                                           0.008),
                          (0.2, -0.4, 0.9, -1.3, 0.1, 2.0))
    return {"zhang750+h": z, "morawiec+h": m, "li_dtp": dtp, "li_dtp+h": dtp2}


DRIVES_H = _drives_with_harmonics()


@pytest.mark.parametrize("name", list(DRIVES_H))
def test_torque_virtual_work(name):
    drive = DRIVES_H[name]
    plant = pj.PMSM(drive.motor, drive.mechanics)
    y = _random_states(np.random.default_rng(2), drive, 30, 1.0)
    tau = np.asarray(jax.vmap(plant.torque)(y))
    ref = _coenergy_torque(drive, y)
    np.testing.assert_allclose(tau, ref, rtol=1e-12, atol=1e-12 * float(drive.tau_rated))
    # The harmonics contribute (the check is not only the fundamental torque).
    m = drive.motor.ab if drive.dual else drive.motor
    R, Ld, Lq, psi_f, n_p = motor_numbers(m)
    i = np.asarray(y.i_dq)
    k = 3.0 if drive.dual else 1.5
    tau0 = k * n_p * ((Ld * i[:, 0] + psi_f) * i[:, 1] - Lq * i[:, 1] * i[:, 0])
    assert np.abs(tau - tau0).max() > 1e-3 * float(drive.tau_rated)


@pytest.mark.parametrize("name", list(DRIVES_H) + ["zhang750"])
def test_power_balance(name):
    """p_in - p_cu - dW/dt == p_mech at random states and inputs (instantaneous)."""
    drive = DRIVES_H.get(name) or pj.preset(name)
    plant = pj.PMSM(drive.motor, drive.mechanics)
    m = drive.motor.ab if drive.dual else drive.motor
    R, Ld, Lq, _, n_p = motor_numbers(m)
    k = 3.0 if drive.dual else 1.5
    rng = np.random.default_rng(3)
    u_lim = float(drive.inverter.u_lim)
    for _ in range(10):
        y = jax.tree_util.tree_map(lambda a: a[0], _random_states(rng, drive, 1, 1.5))
        u_xy = rng.uniform(-0.2, 0.2, 2) * u_lim if drive.dual else None
        u_ab = rng.uniform(-1, 1, 2) * u_lim
        args = pj.PlantInput(u_ab=jnp.asarray(u_ab), tau_L=float(rng.normal()),
                             u_xy=None if u_xy is None else jnp.asarray(u_xy))
        dy = plant.vector_field(0.0, y, args)
        i_dq = np.asarray(y.i_dq)
        di = np.asarray(dy.i_dq)
        u_dq = rot(-float(y.theta)) @ u_ab
        # The terms written out (amplitude-invariant vectors: power = k u . i).
        p_in = k * u_dq @ i_dq
        p_cu = k * R * i_dq @ i_dq
        dW = k * (Ld * i_dq[0] * di[0] + Lq * i_dq[1] * di[1])
        if drive.dual:
            i_xy, di_xy = np.asarray(y.i_xy), np.asarray(dy.i_xy)
            L_xy = float(drive.motor.L_xy)
            p_in += k * u_xy @ i_xy
            p_cu += k * R * i_xy @ i_xy
            dW += k * L_xy * i_xy @ di_xy
        p_mech = float(plant.torque(y)) * float(y.w_m) / n_p
        scale = abs(p_in) + abs(p_cu) + abs(dW) + abs(p_mech)
        assert p_in - p_cu - dW == pytest.approx(p_mech, abs=1e-12 * scale)
        # `power_balance` returns the same terms.
        pb = [float(x) for x in plant.power_balance(y, args)]
        np.testing.assert_allclose(pb, [p_in, p_cu, dW, p_mech], rtol=1e-12,
                                   atol=1e-13 * scale)


@pytest.mark.parametrize("harmonics", [False, True])
def test_energy_balance_transient(harmonics):
    r"""Free rotor, no load, B = 0: E_in - E_cu = Delta(3/4 i^T L i) + Delta(1/2 J w_M^2).

    The voltage is held over blocks of M = 10 fine samples (h = 5 us), and the plant is
    sampled at every fine sample; within a block the integrands are smooth, so composite
    Simpson per block has error ~ h^4/180 T |d^4p/dt^4| ~ 1e-10 J here (E ~ 10 J). RK4
    with h |lambda| < 0.05 (7th harmonic included) has a local error
    (|lambda| h)^5/120 < 3e-9 per step on the fast terms only, whose effect on the
    integrals is far smaller. Tolerance: 1e-9 of the energy throughput E_in + E_cu.
    Also int tau_M w_M dt = Delta E_kin (the rotor is the only mechanical store).
    """
    drive = pj.preset("zhang750")
    if harmonics:
        drive = with_harmonics(drive, (-5, 7), (0.05, 0.03), (0.3, -0.2))
    R, Ld, Lq, psi_f, n_p = motor_numbers(drive.motor)
    J = float(drive.mechanics.J)
    assert float(drive.mechanics.B) == 0.0
    h, M, n_blocks = 5e-6, 10, 300
    N = n_blocks * M + 1
    t = np.arange(N) * h
    rng = np.random.default_rng(4)
    # a rotating voltage at rising frequency plus random blocks: accelerates the rotor
    tb = t[:-1:M]
    phase = 0.5 * 2.0e5 * tb ** 2
    u_blk = 40.0 * np.stack([np.cos(phase), np.sin(phase)], -1) \
        + 15.0 * rng.normal(size=(n_blocks, 2))
    u_ab = np.concatenate([np.repeat(u_blk, M, axis=0), u_blk[-1:]], 0)
    tr = pj.run_plant(drive, t, u_ab, n_substeps=1)
    i_ab, i_dq = np.asarray(tr.i_ab), np.asarray(tr.i_dq)
    w_M = np.asarray(tr.w_m) / n_p
    tau = np.asarray(tr.tau_M)
    E_in = E_cu = E_mech = 0.0
    for b in range(n_blocks):
        sl = slice(b * M, b * M + M + 1)
        E_in += simpson(1.5 * i_ab[sl] @ u_blk[b], h)
        E_cu += simpson(1.5 * R * np.sum(i_ab[sl] ** 2, -1), h)
        E_mech += simpson(tau[sl] * w_M[sl], h)
    W_mag = 0.75 * (Ld * i_dq[-1, 0] ** 2 + Lq * i_dq[-1, 1] ** 2)
    E_kin = 0.5 * J * w_M[-1] ** 2
    assert np.abs(w_M).max() > 10.0  # the rotor did move (a real transient)
    scale = E_in + E_cu
    assert E_in - E_cu == pytest.approx(W_mag + E_kin, abs=1e-9 * scale)
    assert E_mech == pytest.approx(E_kin, abs=1e-9 * scale)
    assert E_kin > 1e-3 * scale  # the tolerance is well below the mechanical energy


# --------------------------------------------------------------------------------------
# Independent integration (scipy DOP853)
# --------------------------------------------------------------------------------------

def _scipy_reference(drive, t, u_ab, tau_L, x0):
    J, B = float(drive.mechanics.J), float(drive.mechanics.B)
    x = np.asarray(x0, float)
    out = [x]
    T_s = t[1] - t[0]
    for k in range(len(t) - 1):
        sol = solve_ivp(lambda _, xx: dq_rhs(drive.motor, J, B, xx, u_ab[k], tau_L[k]),
                        (0.0, T_s), x, method="DOP853", rtol=1e-11, atol=1e-12)
        x = sol.y[:, -1]
        out.append(x)
    return np.array(out)


@pytest.mark.parametrize("name, i_dq0, w_frac", [
    ("zhang750", (0.0, 3.0), 0.5),
    ("morawiec_ipm3k5", (-2.0, 6.0), 0.8),
])
def test_against_scipy(name, i_dq0, w_frac):
    """Free rotor with saliency, load step and a noisy ZOH voltage vs scipy DOP853.

    RK4 with h = T_s/2 = 25 us and |lambda| h < 0.03 (|lambda| <= max(R/L, w) < 1000 1/s)
    has a local relative error ~ (|lambda| h)^5/120 < 2e-10, global over 1600 steps a few
    1e-8 at most; DOP853 at rtol 1e-11: tolerance 1e-7 of each signal's range.
    """
    drive = pj.preset(name)
    R, Ld, Lq, psi_f, n_p = motor_numbers(drive.motor)
    w0 = w_frac * float(drive.w_rated)
    theta0 = 0.3
    T_s, N = 5e-5, 800
    t = np.arange(N) * T_s
    rng = np.random.default_rng(5)
    u_dq = steady_u_dq(drive.motor, np.asarray(i_dq0), w0)
    th = theta0 + w0 * (t + T_s / 2)
    u_ab = np.einsum("kij,j->ki", np.stack([rot(a) for a in th]), u_dq) \
        + 0.05 * np.linalg.norm(u_dq) * rng.normal(size=(N, 2))
    tau0 = 1.5 * n_p * (psi_f + (Ld - Lq) * i_dq0[0]) * i_dq0[1]
    tau_L = np.where(t < 0.02 - T_s / 2, tau0, 1.5 * tau0)
    tr = pj.run_plant(drive, t, u_ab, tau_L, n_substeps=2, theta0=theta0, w_m0=w0,
                      i_dq0=i_dq0)
    ref = _scipy_reference(drive, t, u_ab, tau_L, [*i_dq0, theta0, w0])
    sim = np.column_stack([np.asarray(tr.i_dq), np.asarray(tr.theta), np.asarray(tr.w_m)])
    rng_ = np.ptp(ref, axis=0) + np.abs(ref).max(0)
    err = np.abs(sim - ref).max(0) / rng_
    assert np.all(err < 1e-7), err
    # the rotor did respond: speed changed by more than 1 %
    assert np.ptp(ref[:, 3]) > 0.01 * w0
    # stationary current = e^{theta J} i_dq of the reference
    i_ab_ref = np.einsum("kij,kj->ki", np.stack([rot(a) for a in ref[:, 2]]), ref[:, :2])
    np.testing.assert_allclose(np.asarray(tr.i_ab), i_ab_ref, atol=1e-7 * rng_[:2].max())


# --------------------------------------------------------------------------------------
# Dual three-phase: x-y subspace
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("phases", [None, (0.4, -1.0)])
def test_dual_three_phase_short_circuit(phases):
    r"""Short-circuited DTP machine at imposed speed w.

    The 5th/7th PM-flux harmonics map to x-y only (test_frames), where the PM flux of
    signed order h is psi_h e^{-j(h theta + phi)} (psi_h = psi_f a_h / |h|), so
    L_xy di/dt = -R i - w d psi/dtheta has the periodic solution i = I_h e^{-j h w t},
    I_h = j h w psi_h e^{-j phi} / (R - j h w L_xy), |I_h| = |E_h| / |R + j h w L_xy|,
    |E_h| = w psi_f a_h. The alpha-beta current has no 5th/7th harmonic: in dq it stays
    at the constant solution of (R + w J L) i = -w J [psi_f, 0].
    Tolerance 1e-7: RK4's relative error on the forced response ~ z^4/120 = 5e-9 with
    z = 7 w h = 0.0275, and the start transient has decayed to e^{-20} after 40 ms.
    """
    drive = pj.preset("li_dtp")
    if phases is not None:
        harm = drive.motor.ab.harmonics
        drive = with_harmonics(drive, harm.order, harm.amplitude, phases)
    plant = pj.PMSM(drive.motor, drive.mechanics)
    R, Ld, Lq, psi_f, n_p = motor_numbers(drive.motor.ab)
    L_xy = float(drive.motor.L_xy)
    harm = drive.motor.ab.harmonics
    w = float(drive.w_rated)             # 100 pi rad/s: one period = 0.02 s
    T_s = 1.25e-5                        # 1600 samples per period
    n_per = 1600
    N = 3 * n_per                        # 40 ms transient (20 L_xy/R) + 1 period
    Jm = np.array([[0.0, -1.0], [1.0, 0.0]])
    i_dq_ss = np.linalg.solve(R * np.eye(2) + w * Jm @ np.diag([Ld, Lq]),
                              -w * Jm @ np.array([psi_f, 0.0]))
    y0 = pj.PlantState(i_dq=jnp.asarray(i_dq_ss), theta=jnp.asarray(0.0),
                       w_m=jnp.asarray(w), i_xy=jnp.zeros(2))
    args = pj.PlantInput(u_ab=jnp.zeros(2), tau_L=0.0, u_xy=jnp.zeros(2), free=0.0)

    @jax.jit
    def run(y0):
        def step(y, _):
            y1 = pj.integrate(plant.vector_field, y, args, T_s, solver=pj.RK4(),
                              n_substeps=1)
            return y1, (y.i_dq, y.i_xy, y.theta, y.w_m)

        return jax.lax.scan(step, y0, None, length=N)[1]

    i_dq, i_xy, theta, w_m = (np.asarray(a) for a in run(y0))
    np.testing.assert_allclose(w_m, w, rtol=0, atol=0)
    np.testing.assert_allclose(theta, w * T_s * np.arange(N), rtol=1e-12)
    # alpha-beta: no harmonic at all (constant in dq)
    np.testing.assert_allclose(i_dq, np.broadcast_to(i_dq_ss, i_dq.shape), rtol=0,
                               atol=1e-10 * np.linalg.norm(i_dq_ss))
    # x-y: phasors of the last full period by DFT (rotations +5w and -7w: bins 5, -7)
    z = i_xy[-n_per:, 0] + 1j * i_xy[-n_per:, 1]
    tk = T_s * np.arange(N)[-n_per:]
    z_ref = np.zeros(n_per, complex)
    for h, a, ph in zip(harm.order, np.asarray(harm.amplitude), np.asarray(harm.phase)):
        assert abs(h) in (5, 7)
        psi_h = psi_f * a / abs(h)
        I_h = 1j * h * w * psi_h * np.exp(-1j * ph) / (R - 1j * h * w * L_xy)
        assert abs(I_h) == pytest.approx(w * psi_f * a / abs(R + 1j * abs(h) * w * L_xy))
        z_ref += I_h * np.exp(-1j * h * w * tk)
        # DFT coefficient of the rotation -h w
        c = np.mean(z * np.exp(1j * h * w * tk))
        assert abs(c - I_h) < 1e-7 * abs(I_h), (h, c, I_h)
    np.testing.assert_allclose(z, z_ref, rtol=0, atol=1e-7 * np.abs(z_ref).max())
    assert np.abs(z_ref).max() > 0.1  # a sizeable current (not a trivial zero)
