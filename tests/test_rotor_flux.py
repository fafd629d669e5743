"""morawiec2023's rotor-flux observer: its machine model is the plant's, the slot-harmonic
option of the preset, the Floquet analysis, the sign choice (printed speed law unstable,
derived stable, by linearisation and by running the discrete observer), the k_c effect at
low regenerating speed, zero steady-state error in both directions, replay = in-loop."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import RotorFluxObserver, make_observer
from pmsmjax.observers._rotor_flux import current_rhs_ab, rotor_flux_ab, torque_ab


DRIVE = pj.preset("morawiec_ipm3k5")
M = DRIVE.three_phase_motor
I_B = DRIVE.base.I_b
W_R = DRIVE.w_rated


def _random_points(n, seed):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-np.pi, np.pi, n), rng.uniform(-2, 2, n) * W_R,
            rng.uniform(-1.5, 1.5, (n, 2)) * I_B, rng.uniform(-1, 1, (n, 2)) * 285.0)


def test_paper_model_equals_the_plant():
    """morawiec2023 (1)-(2) with (5)-(6), (36)-(40) is the plant's flux-linkage model in
    the stationary frame, and (3) with (L_d - L_q) i_d i_q is the plant's torque (the
    printed i_alpha i_beta is not)."""
    plant = pj.PMSM(M, DRIVE.mechanics)
    th, w, i_ab, u_ab = _random_points(200, 0)

    def one(th, w, i_ab, u_ab):
        y = pj.PlantState(i_dq=pj.park(i_ab, th), theta=th, w_m=w)
        dy = plant.vector_field(0.0, y, pj.PlantInput(u_ab=u_ab, tau_L=0.0))
        # i_ab = exp(theta J) i_dq -> di_ab/dt = exp(theta J)(di_dq/dt + w J i_dq)
        di_ab = pj.rotate(dy.i_dq + w * pj.jmul(y.i_dq), th)
        return di_ab, current_rhs_ab(M, th, w, i_ab, u_ab), plant.torque(y), \
            torque_ab(M, th, i_ab)

    # one program (op by op, each small operation would compile on its own)
    di_plant, di_paper, tau_plant, tau_paper = jax.jit(jax.vmap(one))(
        *map(jnp.asarray, (th, w, i_ab, u_ab)))
    np.testing.assert_allclose(np.asarray(di_paper), np.asarray(di_plant), rtol=1e-10,
                               atol=1e-9 * float(jnp.max(jnp.abs(di_plant))))
    np.testing.assert_allclose(np.asarray(tau_paper), np.asarray(tau_plant), rtol=1e-10,
                               atol=1e-10)
    # the printed reluctance term (L_d - L_q) i_alpha i_beta differs
    printed = 1.5 * M.n_p * (M.psi_f * (np.cos(th) * i_ab[:, 1] - np.sin(th) * i_ab[:, 0])
                             + (M.L_d - M.L_q) * i_ab[:, 0] * i_ab[:, 1])
    assert np.max(np.abs(printed - np.asarray(tau_plant))) > 0.1 * DRIVE.tau_rated
    # lambda in rotor coordinates: [L_d/L_q (psi_f + (L_d - L_q) i_d), (L_q - L_d) i_q]
    lam_dq = pj.park(rotor_flux_ab(M, jnp.asarray(th), jnp.asarray(i_ab)), jnp.asarray(th))
    i_dq = pj.park(jnp.asarray(i_ab), jnp.asarray(th))
    want = jnp.stack([M.L_d / M.L_q * (M.psi_f + (M.L_d - M.L_q) * i_dq[:, 0]),
                      (M.L_q - M.L_d) * i_dq[:, 1]], -1)
    np.testing.assert_allclose(np.asarray(lam_dq), np.asarray(want), rtol=1e-12,
                               atol=1e-14)


def test_preset_slot_harmonic_is_an_option_and_off_by_default():
    assert DRIVE.motor.harmonics is None
    d = pj.preset("morawiec_ipm3k5", slot_harmonic=0.03)
    assert d.motor.harmonics.order == (-17, 19)
    # in rotor coordinates the -17/+19 pair is an 18th-order ripple of the PM flux
    th = jnp.linspace(0, 2 * np.pi, 360, endpoint=False)
    psi = np.asarray(d.motor.psi_pm_dq(th))
    spec = np.abs(np.fft.rfft(psi[:, 0] - psi[:, 0].mean())) / 180
    assert np.argmax(spec) == 18
    # back-EMF: 3 % per harmonic of the fundamental -> PM-flux ripple 0.03 (1/17 + 1/19)
    assert spec[18] == pytest.approx(M.psi_f * 0.03 * (1 / 17 + 1 / 19), rel=1e-9)
    t = pj.preset("morawiec_ipm3k5", trapezoid=0.05)
    assert t.motor.harmonics.order == (-5, 7)
    with pytest.raises(ValueError, match="unknown option.*slot_harmonik.*slot_harmonic"):
        pj.preset("morawiec_ipm3k5", slot_harmonik=0.03)
    with pytest.raises(ValueError, match="has no options"):
        pj.preset("zhang750", slot_harmonic=0.03)
    with pytest.raises(ValueError, match="slot_harmonic"):
        pj.preset("morawiec_ipm3k5", slot_harmonic=-0.1)


def test_floquet_equals_eigenvalues_for_angle_independent_dynamics():
    """For an observer whose error dynamics do not depend on the rotor angle the
    Floquet exponents are the eigenvalues of the linearisation (mod 2 pi j / T)."""
    d = pj.preset("zhang750")
    obs = make_observer("leso", d)
    w, i = 0.4 * d.w_rated, jnp.array([0.0, 3.0])
    F = analysis.floquet(obs, d.three_phase_motor, w, i, n_steps=16)
    ev = np.linalg.eigvals(np.asarray(analysis.linearization(obs, d.three_phase_motor, w, i)))
    # (a double pole of the critically damped design: its split is ~ sqrt(round-off))
    np.testing.assert_allclose(np.sort(np.asarray(F.exponents).real), np.sort(ev.real),
                               rtol=1e-4)
    np.testing.assert_allclose(float(jnp.sum(F.exponents.real)), float(np.sum(ev.real)),
                               rtol=1e-9)
    assert bool(F.stable)


@pytest.fixture(scope="module")
def stability_maps():
    ws = jnp.array([-1.5, -1.0, -0.5, -0.2, 0.2, 0.5, 1.0, 1.5]) * W_R
    iqs = jnp.array([-0.9, 0.0, 0.9]) * I_B

    @jax.jit
    def run(obs):
        def one(w, iq):
            i = jnp.stack([-0.05 * I_B, iq])
            return (analysis.floquet(obs, M, w, i, n_steps=64).max_real,
                    jnp.max(jnp.real(jnp.linalg.eigvals(
                        analysis.linearization(obs, M, w, i)))))
        return jax.vmap(lambda w: jax.vmap(lambda q: one(w, q))(iqs))(ws)

    return {s: run(RotorFluxObserver.from_drive(DRIVE, speed_sign=s))
            for s in ("derived", "printed")}


def test_printed_speed_law_is_unstable_and_the_derived_one_stable(stability_maps):
    """Linearisation (averaged and Floquet) at 0.2-1.5 p.u., both directions, loads
    -0.9, 0, 0.9 p.u.: the printed sign of (22)/(32) has a right-half-plane exponent
    everywhere, the derived sign none up to 1 p.u.; at 1.5 p.u. with the chosen
    gamma = 1.0 p.u. the motoring 0.9 p.u. load is unstable (documented), the
    regenerating one and no load stable."""
    fl, av = stability_maps["printed"]
    assert float(jnp.min(fl)) > 100.0 and float(jnp.min(av)) > 100.0
    fl, av = stability_maps["derived"]
    assert float(jnp.max(fl[1:-1])) < -1.0 and float(jnp.max(av[1:-1])) < -1.0
    # rows -1.5 and +1.5 p.u.; columns i_q -0.9, 0, 0.9 p.u. (motoring: w i_q > 0)
    assert float(fl[0, 0]) > 10.0 and float(fl[-1, -1]) > 10.0
    assert float(jnp.max(fl[0, 1:])) < -1.0 and float(jnp.max(fl[-1, :-1])) < -1.0


def test_printed_sign_diverges_and_derived_converges_in_the_discrete_observer():
    """The real discrete observer in a loop with ideal current control (0.5 p.u., 0.5 p.u.
    current) from 2 deg and 1 % speed error: the printed sign runs away, the derived
    one converges. (0.6 s, 3960 steps: the derived sign's program is the two tests'
    below.)"""
    w, i = 0.5 * W_R, jnp.array([-0.05, 0.5]) * I_B
    x0 = jnp.array([0.0, 0.0, math.radians(2.0), 0.01 * w])
    out = {}
    for s in ("derived", "printed"):
        obs = RotorFluxObserver.from_drive(DRIVE, speed_sign=s)
        xs = analysis.discrete_error_run(obs, M, w, i, 1 / 6600, x0, 3960)  # 0.6 s
        out[s] = np.asarray(xs)
    assert abs(out["derived"][-1, 2]) < 1e-3 * math.radians(2.0)
    assert np.max(np.abs(out["printed"][:, 2])) > 0.5 or not np.all(np.isfinite(
        out["printed"]))


def test_gamma_2_is_beyond_the_sampling_limit_with_the_fig16b_model():
    """The observer's L_q = 0.3 L_qN (Fig. 16(b)) at 0.2 p.u. with 0.33 p.u. current,
    ideal current control: gamma = 2.0 p.u. runs into a limit cycle at 6.6 kHz but
    converges at 66 kHz (a discretisation limit, not a continuous-time instability);
    the default 1.0 p.u. converges at 6.6 kHz to the same steady offset."""
    from pmsmjax import scale_motor

    w, i = 0.2 * W_R, jnp.array([-0.034, 0.33]) * I_B
    tail = {}
    for gamma, fs in ((2.0, 6600), (2.0, 66000), (1.0, 6600)):
        obs = RotorFluxObserver.from_pu(DRIVE, motor=scale_motor(M, {"L_q": 0.3}),
                                        gamma=gamma)
        xs = np.asarray(analysis.discrete_error_run(obs, M, w, i, 1 / fs, jnp.zeros(4),
                                                    int(0.6 * fs)))
        tail[gamma, fs] = xs[-int(0.1 * fs):]
    assert np.std(tail[2.0, 6600][:, 3]) > 0.5 * W_R
    # the steady offset is the continuous error dynamics' equilibrium (SciPy's root of
    # error_rhs, in scaled coordinates, from the origin), the same for both gammas:
    # measured 1.4e-5 rad from the discrete runs' means (the discretisation and the
    # tail's last decay); allow 1e-4 rad
    import scipy.optimize

    from pmsmjax.observers import OperatingPoint

    op = OperatingPoint(w, i)
    f = jax.jit(lambda x, obs: obs.error_rhs(x, op, M))  # one program for both gammas
    for k in ((2.0, 66000), (1.0, 6600)):
        obs = RotorFluxObserver.from_pu(DRIVE, motor=scale_motor(M, {"L_q": 0.3}),
                                        gamma=k[0])
        sc = np.asarray(obs.error_scale(op, M))
        z = scipy.optimize.fsolve(lambda z: np.asarray(f(jnp.asarray(z * sc), obs)) / sc,
                                  np.zeros(4), xtol=1e-12)
        assert np.max(np.abs(np.asarray(f(jnp.asarray(z * sc), obs)) / sc)) < 1e-10
        x_eq = z * sc
        assert abs(x_eq[2]) > 0.1  # a real offset (the model's L_q is 0.3 of the plant's)
        assert np.std(tail[k][:, 3]) < 1e-3 * W_R, k
        assert np.mean(tail[k][:, 2]) == pytest.approx(x_eq[2], abs=1e-4), k


def test_kc_speeds_up_the_slowest_mode_at_low_regenerating_speed():
    """Fig. 13's operating point (0.025 p.u., T_L = -0.75 p.u.): with k_c = 0 the slowest
    Floquet exponent is near zero (averaging even calls it unstable), with k_c = 1.5
    several times faster."""
    i = jnp.array([-0.05, -0.82]) * I_B
    w = 0.025 * W_R
    mr = {kc: float(analysis.floquet(RotorFluxObserver.from_pu(DRIVE, k_c=kc), M, w, i,
                                     n_steps=64).max_real) for kc in (0.0, 1.5)}
    assert -1.0 < mr[0.0] < 0.0
    assert mr[1.5] < 10 * mr[0.0]


@pytest.fixture(scope="module")
def closed_loop_runs():
    """Speed control at +-0.5 p.u. with a load of 0.3 p.u. of rated torque, exact
    parameters, from a 0.2 rad initial angle error (0.6 s at 6.6 kHz)."""
    obs = make_observer("rotor-flux", DRIVE)
    foc = pj.FOC.from_drive(DRIVE, alpha_s=2 * math.pi * 5.0)
    runs = {}
    for sgn in (1.0, -1.0):
        w = sgn * 0.5 * W_R
        sc = pj.Scenario(t_end=0.6, w_m_ref=pj.Profile.constant(w),
                         tau_L=pj.Profile.constant(sgn * 0.3 * DRIVE.tau_rated))
        runs[sgn] = pj.simulate(DRIVE, foc, obs, sc, T_s=1 / 6600, w_m0=w, theta0=0.2,
                                theta_hat0=0.0, w_hat0=w)
    return obs, runs


def test_zero_steady_state_error_in_both_directions():
    """Exact parameters, constant speed +-0.5 p.u. with +-0.5 p.u. current (ideal current
    control), 0.2 rad and 2 % speed error at the start: the discrete observer converges
    to zero error in both directions. (0.6 s, 3960 steps: the program of the gamma test
    above; 0.5 s was enough.)"""
    for sgn in (1.0, -1.0):
        w, i = sgn * 0.5 * W_R, jnp.array([-0.05, sgn * 0.5]) * I_B
        x0 = jnp.array([0.0, 0.0, 0.2, 0.02 * w])
        obs = make_observer("rotor-flux", DRIVE)
        xs = np.asarray(analysis.discrete_error_run(obs, M, w, i, 1 / 6600, x0, 3960))
        assert np.max(np.abs(xs[-330:, 2])) < 1e-6, (sgn, xs[-1])
        assert np.max(np.abs(xs[-330:, 3])) < 1e-6 * W_R, (sgn, xs[-1])


def test_closed_loop_speed_control_converges_in_both_directions(closed_loop_runs):
    """In the loop (speed control, mechanics) the drive's own slow mode (about 1.6 Hz,
    lightly damped) remains; the angle error still falls from 0.2 rad below 0.02 rad."""
    _, runs = closed_loop_runs
    for sgn, traj in runs.items():
        err = np.asarray(pj.angle_error(traj.theta, traj.theta_hat))
        tail = slice(-660, None)  # the last 0.1 s
        assert np.max(np.abs(err[tail])) < 0.02, (sgn, np.max(np.abs(err[tail])))
        assert np.max(np.abs(np.asarray(traj.w_m - traj.w_hat)[tail])) < 0.02 * W_R
        assert abs(float(err[0])) > 0.19  # it did start from the 0.2 rad error


def test_replay_equals_in_loop(closed_loop_runs):
    obs, runs = closed_loop_runs
    traj = runs[1.0]
    est = pj.replay_estimates(obs, traj, theta0=0.0, w0=0.5 * W_R)
    np.testing.assert_allclose(np.asarray(est.theta_hat), np.asarray(traj.theta_hat),
                               rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(est.w_hat), np.asarray(traj.w_hat), rtol=1e-12,
                               atol=1e-9)
    for k in ("s_omega", "theta_lambda"):
        np.testing.assert_allclose(np.asarray(est.extras[k]), np.asarray(traj.extras[k]),
                                   rtol=1e-9, atol=1e-12)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="speed_sign.*derived, printed.*'plus'"):
        RotorFluxObserver.from_drive(DRIVE, speed_sign="plus")
    with pytest.raises(ValueError, match="unknown gain.*c_beta"):
        RotorFluxObserver.from_pu(DRIVE, c_beta=1.0)
    with pytest.raises(ValueError, match="gamma"):
        RotorFluxObserver.from_drive(DRIVE, gamma=-1.0)


def test_contract_jacobian_equals_finite_differences():
    """The averaged and the instantaneous linearisation (jacfwd of `error_rhs`) against
    central differences, at a loaded operating point and off the origin."""
    from pmsmjax.observers import OperatingPoint

    obs = make_observer("rotor-flux", DRIVE)
    w, i = 0.4 * W_R, jnp.array([-0.2, 0.6]) * I_B
    x = jnp.array([0.05, -0.03, 0.1, 2.0])
    D = obs.error_scale(OperatingPoint(w, i), M)
    rhs = jax.jit(lambda v, op: obs.error_rhs(v, op, M))  # one program per angle's structure
    for theta in (None, 1.1):
        op = OperatingPoint(w, i, theta)
        A = np.asarray(analysis.linearization(obs, M, w, i, x=x, theta=theta))
        f = lambda v: np.asarray(rhs(jnp.asarray(v), op))  # noqa: E731
        h = 1e-6 * np.asarray(D)
        fd = np.stack([(f(x + h[j] * np.eye(4)[j]) - f(x - h[j] * np.eye(4)[j])) / (2 * h[j])
                       for j in range(4)], 1)
        np.testing.assert_allclose(A * np.asarray(D)[None, :], fd * np.asarray(D)[None, :],
                                   rtol=1e-6, atol=1e-6 * np.max(np.abs(A * np.asarray(D))))


def test_printed_matrix_35_and_the_exact_spectra_differ_as_documented():
    from pmsmjax.papers import morawiec2023 as mp

    # (35): the angle row decouples, so -c_theta is always an eigenvalue
    A = np.asarray(mp.matrix35(0.3, 0.5, 3.0, 0.05, 0.5, 0.7, 1.0))
    assert np.min(np.abs(np.linalg.eigvals(A) + 0.7)) < 1e-12
    # Fig. 3: with c_theta = 0 (35) has a zero eigenvalue, with 0.1 it is stable; the
    # observer's own linearisation at standstill keeps a zero eigenvalue either way
    i = jnp.asarray(mp.working_point(1.0)) * I_B
    for c_theta in (0.0, 0.1):
        ev = np.linalg.eigvals(np.asarray(mp.matrix35(0.0, 1.0, 3.0, 0.05, 0.5, c_theta,
                                                      2.0)))
        assert (np.min(np.abs(ev)) < 1e-12) == (c_theta == 0.0)
        assert np.max(ev.real) < 1e-12
        obs = RotorFluxObserver.from_pu(DRIVE, c_lambda=0.05, k_c=0.5, c_theta=c_theta)
        ex = np.linalg.eigvals(np.asarray(analysis.linearization(obs, M, 0.0, i)))
        assert np.min(np.abs(ex)) < 1e-9
    # Fig. 4(b): (35) is unstable from k_c = 1.2 at 1 p.u.; the implemented observer
    # (derived signs) is stable up to k_c = 1.6 (Floquet; at 2.0 it is +0.008 p.u.)
    s4 = mp.spectrum_sweep("fig4b", n_floquet=16)
    assert np.max(s4.printed.real[s4.values >= 1.2]) > 0
    assert np.max(s4.floquet.real[s4.values <= 1.6]) < 0


def test_period_average_is_exact_with_eight_angles():
    from pmsmjax.observers import OperatingPoint

    obs = make_observer("rotor-flux", DRIVE)
    x = jnp.array([0.3, -0.2, 0.4, 20.0])
    op = OperatingPoint(0.4 * W_R, jnp.array([-2.0, 6.0]))
    th = jnp.arange(64) * 2 * np.pi / 64
    f64 = jax.jit(lambda th: jnp.mean(jax.vmap(lambda t: obs.error_rhs(
        x, OperatingPoint(op.w_m, op.i_dq, t), M))(th), 0))(th)  # one program
    np.testing.assert_allclose(np.asarray(jax.jit(lambda: obs.error_rhs(x, op, M))()),
                               np.asarray(f64), rtol=1e-12)


def _worst_discrete_pole(obs, drive, T_s, speed_pu=0.5, i_pu=(0.05, 0.5), n_angles=12):
    """Largest |pole| of one real step over an electrical period of rotor angles."""
    from pmsmjax import analysis

    W, Ib = float(drive.w_rated), float(drive.base.I_b)
    w, i_dq = speed_pu * W, (i_pu[0] * Ib, i_pu[1] * Ib)
    return max(float(np.abs(np.asarray(analysis.discrete_poles(
        obs, drive.three_phase_motor, w, i_dq, T_s, theta_k=th))).max())
        for th in np.linspace(0.0, 2 * np.pi, n_angles, endpoint=False))


@pytest.mark.parametrize("T_s", [62.5e-6, 125e-6])
def test_default_gamma_keeps_the_discrete_speed_loop_stable_on_stumper_mt5(T_s):
    """On stumper_mt5 ((psi_f/L_d)^2 six times the paper machine's in p.u.) the paper's
    gamma = 1.0 p.u. puts a pole of the real discrete step outside the unit circle (a
    replay from the true state ran away after 0.1 s); the default design's scaled gamma
    (`gamma_pu_for`) keeps every pole inside, and the replay of a run turning from the
    first sample, started at zero speed and a wrong angle, locks and stays finite."""
    from pmsmjax.observers import RotorFluxObserver
    from pmsmjax.observers._rotor_flux import gamma_pu_for

    drive = pj.preset("stumper_mt5")
    assert gamma_pu_for(pj.preset("morawiec_ipm3k5")) == 1.0
    assert gamma_pu_for(drive) < 0.2
    paper = RotorFluxObserver.from_pu(drive, gamma=1.0)
    default = RotorFluxObserver.from_drive(drive)
    assert _worst_discrete_pole(paper, drive, T_s) > 1.005
    assert _worst_discrete_pole(default, drive, T_s) < 0.9995
    W = float(drive.w_rated)
    sc = pj.Scenario(t_end=0.3, w_m_ref=pj.Profile.constant(0.3 * W))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_s,
                     w_m0=0.3 * W, theta0=2.0)
    th, wh = pj.replay(default, tr, theta0=0.0, w0=0.0)
    err = np.asarray(pj.wrap_angle(np.asarray(tr.theta) - np.asarray(th)))
    assert np.all(np.isfinite(np.asarray(th))) and np.all(np.isfinite(np.asarray(wh)))
    st = pj.lock_status(np.asarray(tr.t), err)
    assert bool(st["acquired"]) and not bool(st["lost"])
    t = np.asarray(tr.t)
    assert np.abs(err[t > 0.2]).max() < np.radians(0.5)


def test_a_runaway_design_keeps_its_estimate_finite_and_reports_the_lost_lock():
    """gamma = 1.0 p.u. on stumper_mt5 at 125 us runs away (a replay used to end in NaN):
    the observer holds its state where a step would leave it non-finite, so every
    estimate is finite and `lock_status` reports the lost lock."""
    from pmsmjax.observers import RotorFluxObserver

    drive = pj.preset("stumper_mt5")
    W = float(drive.w_rated)
    obs = RotorFluxObserver.from_pu(drive, gamma=1.0)
    # 0.3 s at 125 us: the programs (run, replay, lock) of the default-gamma test
    sc = pj.Scenario(t_end=0.3, w_m_ref=pj.Profile.constant(0.5 * W))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc,
                     T_s=125e-6, w_m0=0.5 * W)
    th, wh = pj.replay(obs, tr, theta0=0.0, w0=0.5 * W)
    assert np.all(np.isfinite(np.asarray(th))) and np.all(np.isfinite(np.asarray(wh)))
    err = np.asarray(pj.wrap_angle(np.asarray(tr.theta) - np.asarray(th)))
    st = pj.lock_status(np.asarray(tr.t), err)
    assert bool(st["lost"]) or not bool(st["acquired"])
