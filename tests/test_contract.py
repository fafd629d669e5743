"""The observer contract, for every registered observer: the continuous error dynamics
are the observer that runs (discrete Jacobian = I + T_s A + O(T_s^2); a closed-loop run
from a perturbed state follows the continuous dynamics), the state maps invert each other,
designs round-trip, extras reach `simulate` and `replay`, and the generic analysis agrees
with zhang2022's closed forms."""

import functools
import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.analysis._args import as_arrays
from pmsmjax.observers import (
    OperatingPoint,
    PlantPoint,
    make_observer,
    observer_class,
    observer_names,
)


DRIVE = pj.preset("zhang750")
# a salient variant, so that every term of the error dynamics matters
SALIENT = pj.replace_params(DRIVE, L_d=1.0e-3, L_q=5.0e-3)
NAMES = observer_names()
OP = (0.5, (0.15, 0.6))  # speed (p.u.), current (p.u.)


def _op(drive, op=OP):
    w, (i_d, i_q) = op
    return w * drive.w_rated, jnp.array([i_d, i_q]) * drive.base.I_b


def _inputs(tree):
    """`tree` with its float values (an observer's design and model, a machine, a speed)
    as arrays: inputs of a compiled program instead of constants compiled into it, so
    that every preset and design reuses one program per observer family (Python ints,
    an observer's counts and sizes, stay as they are)."""
    return as_arrays(tree, jnp.float64, ints=False)


@eqx.filter_jit
def _design_point(obs, plant, w, i):
    """At the operating point (w, i) of `obs`'s error dynamics: their value 1 % of each
    coordinate's scale off the designed equilibrium (`designed_error`), relative to the
    scale; the designed equilibrium; the dynamics there; and the scale."""
    op = OperatingPoint(w, i)
    x_star = obs.designed_error(op, plant)
    scale = obs.error_scale(op, plant)
    near = obs.error_rhs(x_star + 0.01 * scale, op, plant) / scale
    return near, x_star, obs.error_rhs(x_star, op, plant), scale


def test_registry_lists_the_zhang2022_observers_and_rejects_unknown_names():
    assert {"eso", "leso", "afo"} <= set(NAMES)
    with pytest.raises(ValueError, match="Unknown observer 'kalman'.*eso"):
        make_observer("kalman", DRIVE)
    with pytest.raises(ValueError, match="must be a `Drive`"):
        make_observer("eso", DRIVE.motor)


@pytest.mark.parametrize("preset", pj.PRESET_NAMES)
@pytest.mark.parametrize("name", NAMES)
def test_every_observer_has_a_default_design_on_every_preset(name, preset):
    drive = pj.preset(preset)
    obs = make_observer(name, drive)
    assert isinstance(obs, observer_class(name))
    params = obs.design_parameters()
    assert params and set(params) <= set(obs.design_units)
    # the design round-trips through with_design with changed values: each one alone is
    # reported back and leaves the others; all changed at once change the observer's
    # error dynamics (near its designed equilibrium: 1 % of each coordinate's scale off
    # it); and setting the old values again gives back the same observer
    w, i = _op(drive)
    plant = _inputs(drive.three_phase_motor)
    new = {k: 1.25 * float(v) if float(v) != 0 else 0.25 for k, v in params.items()}
    for k in params:
        one = obs.with_design(**{k: new[k]}).design_parameters()
        assert one.keys() == params.keys()
        for j, v in params.items():
            assert float(one[j]) == pytest.approx(new[k] if j == k else float(v),
                                                  rel=1e-12), (k, j)
    changed = obs.with_design(**new)
    assert {k: float(v) for k, v in changed.design_parameters().items()} == \
        pytest.approx(new, rel=1e-12)

    # (one compiled program per family for every preset and design: `_inputs`)
    w_in, i_in = _inputs((w, i))
    near0, _, f_star, scale = map(np.asarray, _design_point(_inputs(obs), plant, w_in, i_in))
    near1 = np.asarray(_design_point(_inputs(changed), plant, w_in, i_in)[0])
    assert np.max(np.abs(near1 - near0)) > 1e-3 * np.max(np.abs(near0))

    back = changed.with_design(**params)
    assert eqx.tree_equal(jax.tree_util.tree_map(np.asarray, back),
                          jax.tree_util.tree_map(np.asarray, obs), rtol=1e-12, atol=0)
    # its error dynamics are finite and vanish at its designed equilibrium
    # (`designed_error`: the origin, or a deliberate lag such as the C-LESO's)
    assert np.all(np.isfinite(f_star))
    np.testing.assert_allclose(f_star / scale, 0.0, atol=1e-9 * float(w))


@pytest.mark.parametrize("name", NAMES)
def test_with_design_rejects_unknown_parameters(name):
    obs = make_observer(name, DRIVE)
    with pytest.raises(ValueError, match="unknown design parameter.*bogus"):
        obs.with_design(bogus=1.0)
    with pytest.raises(ValueError, match="unknown design parameter"):
        make_observer(name, DRIVE, bogus=1.0)


@eqx.filter_jit
def _round_trip(obs, plant, truth, x):
    """`error_state(observer_state(x))` at `truth`, and the coordinates' scale there."""
    back = obs.error_state(obs.observer_state(x, truth, plant), truth, plant)
    return back, obs.error_scale(OperatingPoint(truth.w_m, truth.i_ab), plant)


@pytest.mark.parametrize("name", NAMES)
def test_state_maps_invert_each_other(name):
    obs = make_observer(name, SALIENT)
    plant = SALIENT.three_phase_motor
    truth = PlantPoint(theta=jnp.asarray(0.7), w_m=jnp.asarray(300.0),
                       i_ab=jnp.array([1.2, -0.4]))
    c = obs.coordinates
    x = jnp.resize(jnp.array([0.004, -0.002]), c.n).at[c.angle].set(0.3)
    x = x.at[c.names.index("w")].set(25.0) if "w" in c.names else x
    # (one compiled program; op by op, each of its operations compiled on its own)
    back, D = _round_trip(obs, plant, truth, x)
    # round-off relative to each coordinate's size at that point
    err = np.abs(np.asarray(back) - np.asarray(x))
    assert np.all(err <= 1e-15 + 1e-12 * np.abs(np.asarray(x)) + 1e-13 * np.asarray(D)), err


@eqx.filter_jit
def _step_and_jacobian(obs, plant, w, i, T_s, x):
    """One real step from `x` (`discrete_error_map`, rotor angle 0.3 rad) and its
    Jacobian there as `discrete_jacobian` computes it (forward mode, on the observer's and
    machine's numbers as inputs), in one program per observer family for every period
    (a step of its own would compile the step again)."""
    fn = analysis.discrete_error_map(obs, plant, w, i, T_s, theta_k=0.3)
    return jax.vmap(lambda v: jax.jvp(fn, (x,), (v,)), out_axes=(None, 1))(
        jnp.eye(x.shape[0], dtype=x.dtype))


@pytest.mark.parametrize("name", NAMES)
def test_discrete_step_jacobian_is_identity_plus_Ts_A(name):
    """The Jacobian of one real `step` in error coordinates equals I + T_s A with the
    remainder O(T_s^2): halving T_s quarters it (and it is far below T_s A), at the
    designed equilibrium (`designed_error`)."""
    obs = make_observer(name, SALIENT)
    plant = SALIENT.three_phase_motor
    w, i = _op(SALIENT)
    n = obs.coordinates.n
    # the designed equilibrium and the coordinates' scale (the program of
    # test_every_observer_has_a_default_design_on_every_preset)
    _, x_star, _, D = map(np.asarray, _design_point(_inputs(obs), _inputs(plant),
                                                    *_inputs((w, i))))
    # at the rotor angle of the step where the error dynamics depend on it (the
    # rotor-flux observer's: `OperatingPoint.theta`); the others' do not, and their A is
    # then test_closed_loop_run_follows_the_continuous_error_dynamics's program (an A
    # that missed the angle would fail the O(T_s^2) check below)
    theta = 0.3 if name == "rotor-flux" else None
    A = np.asarray(analysis.linearization(obs, plant, w, i, x=x_star, theta=theta))
    scaled = lambda M: M / D[:, None] * D[None, :]  # noqa: E731
    rem = []
    # T_s |lambda_max| <= 0.1, so that the first-order term dominates
    T0 = min(1e-4, 0.1 / float(np.max(np.abs(np.linalg.eigvals(A)))))
    for T_s in (T0, T0 / 2, T0 / 4):
        x1, Jd = map(np.asarray, _step_and_jacobian(_inputs(obs), _inputs(plant),
                                                    *_inputs((w, i, T_s, x_star))))
        np.testing.assert_allclose((x1 - x_star) / D, 0.0, atol=1e-12)
        r = float(np.max(np.abs(scaled(Jd - np.eye(n) - T_s * A))))
        assert r < 0.1 * float(np.max(np.abs(scaled(T_s * A))))
        rem.append(r)
    for a, b in zip(rem, rem[1:]):
        assert 3.5 < a / b < 4.5, rem


def test_discrete_jacobian_is_the_derivative_of_the_step_and_compiles_once():
    """`discrete_jacobian` against central differences of `discrete_error_map` (run op by
    op, a second route), and one compiled program for other designs, periods, speeds and
    a mismatched plant (the same schedule, `fixed_ratio`: a schedule is a structure, and
    another one compiles its own): their values are the program's inputs."""
    from pmsmjax.analysis._discrete import _discrete_jacobian

    plant = SALIENT.three_phase_motor
    w, i = _op(SALIENT)
    obs = make_observer("leso", SALIENT).with_design(zeta1=0.5, ratio=0.5)
    x = obs.designed_error(OperatingPoint(w, i), plant)
    J = np.asarray(analysis.discrete_jacobian(obs, plant, w, i, 1e-4, x=x, theta_k=0.3))
    fn = analysis.discrete_error_map(obs, plant, w, i, 1e-4, theta_k=0.3)
    D = np.asarray(obs.error_scale(OperatingPoint(w, i), plant))
    h = 1e-6 * D
    fd = np.stack([(np.asarray(fn(x.at[k].add(h[k]))) - np.asarray(fn(x.at[k].add(-h[k]))))
                   / (2 * h[k]) for k in range(len(h))], 1)
    np.testing.assert_allclose(J * D[None, :] / D[:, None], fd * D[None, :] / D[:, None],
                               atol=1e-7)
    n0 = _discrete_jacobian._cached._cache_size()
    other = [analysis.discrete_jacobian(obs.with_design(zeta1=0.7, ratio=0.4), plant, w, i,
                                        1e-4, x=x, theta_k=0.3),
             analysis.discrete_jacobian(obs, plant, 0.5 * w, i, 5e-5, x=x, theta_k=1.0),
             analysis.discrete_jacobian(obs, pj.scale_motor(plant, {"R_s": 1.2}), w, i,
                                        1e-4, x=x, theta_k=0.3)]
    assert _discrete_jacobian._cached._cache_size() == n0
    for J2 in other:  # and the values are used
        assert np.max(np.abs(np.asarray(J2) - J)) > 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_closed_loop_run_follows_the_continuous_error_dynamics(name):
    """From a perturbed state (angle error 4 deg, speed error 2 %), the discrete observer in
    a loop with ideal current control tracks the continuous error dynamics (diffrax)."""
    obs = make_observer(name, SALIENT)
    if name == "rotor-flux":  # the paper's gamma (1.0 p.u.), not the scaled default: the
        # run's 0.15 s then covers the decay this test times
        obs = pj.observers.RotorFluxObserver.from_pu(SALIENT)
    plant = SALIENT.three_phase_motor
    w, i = _op(SALIENT)
    a = obs.coordinates.angle
    # the designed equilibrium and the coordinates' scale (`_design_point`'s program)
    _, x_star, _, D = map(np.asarray, _design_point(_inputs(obs), _inputs(plant),
                                                    *_inputs((w, i))))
    x0 = x_star.copy()
    x0[a] += math.radians(4.0)
    if "w" in obs.coordinates.names:
        x0[obs.coordinates.names.index("w")] += 0.02 * w
    T_s = 2e-5
    # long enough for the slowest linearised mode to decay (30 ms at least), at most 0.5 s:
    # the FA-LESO's slowest mode (-0.31 1/s, its frequency adaptation) would need 26 s
    # (1.3 M steps, 80 s of test) and hardly moves the angle, which has decayed to
    # < 5 % of its start by 0.5 s as for the other observers (checked below)
    ev = np.linalg.eigvals(np.asarray(analysis.linearization(obs, plant, w, i, x=x_star)))
    N = min(max(1500, int(math.ceil(8.0 / -float(np.max(ev.real)) / T_s))), int(0.5 / T_s))
    xs = np.asarray(analysis.discrete_error_run(obs, plant, w, i, T_s, x0, N))
    ts = np.arange(N + 1) * T_s
    # the rotor turns from angle 0 (read only by angle-dependent error dynamics)
    rhs = lambda t, x, args: obs.error_rhs(x, OperatingPoint(w, i, w * t), plant)  # noqa: E731
    # (forward mode: the same solution, without the checkpointing that reverse-mode
    # derivatives need, which compiled slower: 7.8 s instead of 9.1 s for the ten
    # families, CPU time, measured)
    sol = dfx.diffeqsolve(dfx.ODETerm(rhs),
                          dfx.Tsit5(), 0.0, float(ts[-1]), T_s, jnp.asarray(x0),
                          saveat=dfx.SaveAt(ts=jnp.asarray(ts)), max_steps=max(4096, 4 * N),
                          stepsize_controller=dfx.PIDController(rtol=1e-9, atol=1e-12),
                          adjoint=dfx.ForwardMode())
    ys = np.asarray(sol.ys)
    dev = np.max(np.abs((xs - ys) / D))
    size = np.max(np.abs((ys - x_star) / D))
    assert dev < 0.03 * size, (dev, size)
    # and the error decays (the designed equilibrium is stable)
    assert abs(xs[-1, a] - x_star[a]) < 0.05 * math.radians(4.0)


@pytest.mark.parametrize("name", NAMES)
def test_extras_reach_simulate_and_replay(name):
    obs = make_observer(name, DRIVE)
    foc = pj.FOC.from_drive(DRIVE)
    sc = pj.Scenario(t_end=0.01, w_m_imposed=pj.Profile.constant(0.3 * DRIVE.w_rated),
                     i_d_ref=pj.Profile.constant(0.0), i_q_ref=pj.Profile.constant(1.0))
    traj = pj.simulate(DRIVE, foc, obs, sc, T_s=1e-4, w_m0=0.3 * DRIVE.w_rated)
    assert set(traj.extras) == set(type(obs).extras)
    est = pj.replay_estimates(obs, traj, theta0=0.0, w0=0.3 * DRIVE.w_rated)
    for k in type(obs).extras:
        assert traj.extras[k].shape[0] == traj.t.shape[0]
        np.testing.assert_allclose(np.asarray(est.extras[k]), np.asarray(traj.extras[k]),
                                   rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------------------------
# Generic analysis vs zhang2022's closed forms
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["leso", "afo"])
def test_generic_linearisation_has_the_designed_characteristic_polynomial(name):
    """zhang2022 (16)/(18) for the LESO, (53) for the AFO: the poles of the generic
    linearisation at the origin are the designed ones."""
    obs = make_observer(name, SALIENT, w2=2 * math.pi * 70.0, zeta2=0.8)
    plant = SALIENT.three_phase_motor
    w, i = _op(SALIENT)
    A = analysis.linearization(obs, plant, w, i)
    zeta1, w1 = pj.observers.zhang38(w, SALIENT.w_rated)
    want = np.polymul([1.0, 2 * float(zeta1) * float(w1), float(w1) ** 2],
                      [1.0, 2 * 0.8 * obs.design.w2, obs.design.w2 ** 2])
    got = np.asarray(analysis.charpoly(A))
    np.testing.assert_allclose(got, want, rtol=1e-9)
    st = analysis.stability(A)
    assert bool(st.hurwitz) and float(st.max_real) < 0


def _random_designs(n, seed, drive):
    rng = np.random.default_rng(seed)
    w0 = rng.choice([-1.0, 1.0], n) * rng.uniform(0.03, 1.3, n) * drive.w_rated
    i0 = rng.uniform(-2.0, 2.0, (n, 2)) * drive.base.I_b
    return w0, i0, rng.uniform(0.05, 5.0, n), rng.uniform(0.03, 2.0, n)


# The classifier's compile options under quick compiles: LLVM at -O1 (XLA's own kernel
# emitters off, as for quick compiles) runs the 2,500 designs as fast as full
# optimisation (2.1 s per machine) for half its compile (5.8 s instead of 11.5 s; quick
# compiles: 2.4 s, but 7.3 s per machine; CPU time, 2-core Intel Xeon, measured)
_LONG_RUN = (None if pj.runtime.long_run_compiler_options() is None
             else {"xla_backend_optimization_level": 1})


@pytest.fixture(scope="module")
def generic_classifier():
    # 2,500 designs per machine: the run outweighs the compile (pmsmjax.runtime, quick
    # compiles; both machines in one process, 2-core Intel Xeon: 18 s compiled at full
    # optimisation, 25 s with quick compiles; BENCHMARKS.md; 13 s at -O1: `_LONG_RUN`)
    @functools.partial(jax.jit, compiler_options=_LONG_RUN)
    def run(motor, motor_hat, w0, i0, z1, r):
        def one(w, i, a, b):
            obs = pj.LESOObserver(motor_hat, pj.ESODesign.fixed_ratio(a, b))
            return analysis.classify(obs, motor, w, i, method="generic")
        return jax.vmap(one)(w0, i0, z1, r)
    return run


@pytest.mark.parametrize("drive", [DRIVE, pj.replace_params(DRIVE, L_d=1e-3, L_q=12e-3)],
                         ids=["table1", "salient"])
def test_generic_route_agrees_with_the_quartic_on_2500_designs(drive, generic_classifier):
    """zhang2022 (34)-(36) in closed form (the fast path) against the generic route, on
    2,500 random designs and operating points (both signs of speed, any current; 10,000
    found no more disagreements, at four times the run)."""
    m = drive.three_phase_motor
    w0, i0, z1, r = _random_designs(2_500, seed=7, drive=drive)
    cf = analysis.classify_designs(m, w0, i0, z1, r)
    ge = generic_classifier(m, m, jnp.asarray(w0), jnp.asarray(i0), jnp.asarray(z1),
                            jnp.asarray(r))
    st_cf, st_ge = np.asarray(cf.status), np.asarray(ge.status)
    ok = (st_cf >= 0) & (st_ge >= 0)
    assert ok.mean() > 0.999, np.unique(st_ge, return_counts=True)
    np.testing.assert_array_equal(st_cf[ok], st_ge[ok])
    np.testing.assert_array_equal(np.asarray(cf.n_nonzero)[ok], np.asarray(ge.n_nonzero)[ok])
    a = np.sort(np.nan_to_num(np.asarray(cf.theta)[ok], nan=9.0), -1)[:, :3]
    b = np.sort(np.nan_to_num(np.asarray(ge.theta)[ok], nan=9.0), -1)[:, :3]
    np.testing.assert_allclose(a, b, atol=1e-7)
    if drive is not DRIVE:
        assert np.sum(st_cf == 1) > 100  # the salient machine has infeasible designs


def _eso_routes(m, f, w, i, a):
    """The equilibria of the ESO with fal feedback (`a`, eta = 5 % of the PM flux) and
    the model `m` with its four parameters scaled by `f` on the plant `m`, at speed `w`
    and current `i`: by the generic route and by zhang2022's reduction
    (`eso_equilibria`)."""
    mh = pj.PMSMParams(R_s=m.R_s * f[0], L_d=m.L_d * f[1], L_q=m.L_q * f[2],
                       psi_f=m.psi_f * f[3], n_p=m.n_p)
    obs = pj.ESOObserver(mh, pj.ESODesign.zhang38(DRIVE.w_rated), a=a, eta=0.05 * m.psi_f)
    ge = analysis.equilibria_traced(obs, m, OperatingPoint(w, i), method="generic")
    eso = analysis.eso_equilibria(w, i, obs.linear_gains(w, i), m, mh, a=a,
                                  eta=0.05 * m.psi_f)
    return ge, eso


@pytest.fixture(scope="module")
def eso_routes():
    """`_eso_routes` at 400 random operating points and mismatched models (about 200 of
    each feedback, linear and fal), on a salient machine; and last, the default ESO
    (matched) at `OP` on `SALIENT` (test_auto_method_takes_the_eso_reduction_for_fal):
    one compiled program for both tests. Returns (generic, reduction, a) as NumPy."""
    n = 400  # the run, not the compile, grows with n
    rng = np.random.default_rng(11)
    drive = pj.replace_params(DRIVE, L_d=1.5e-3, L_q=4e-3)
    w0, i0, _, _ = _random_designs(n, seed=5, drive=drive)
    fac = rng.uniform(0.6, 1.5, (n, 4))
    a = np.where(rng.uniform(size=n) < 0.5, 1.0, 0.6)
    obs = make_observer("eso", SALIENT)
    m = SALIENT.three_phase_motor
    # the last point is that observer, built from its numbers
    assert obs.design == pj.ESODesign.zhang38(DRIVE.w_rated) and obs.motor == m
    assert obs.eta == 0.05 * m.psi_f and drive.w_rated == SALIENT.w_rated == DRIVE.w_rated
    w, i = _op(SALIENT)
    motors = [drive.three_phase_motor] * n + [m]
    plant = jax.tree_util.tree_map(lambda *v: jnp.asarray(v), *motors)
    # 401 designs: with full optimisation its compile outgrows its run. One design after
    # another (`lax.map`): under `jax.vmap` every design ran the loops of the slowest
    # (the reduction's 400: 4.1 s instead of 0.8 s of CPU, measured); both routes
    # under vmap: test_generic_route_agrees_with_the_quartic_on_2500_designs,
    # test_statuses_under_vmap_never_nan_or_raise, tests/test_equilibria.py
    ge, eso = jax.jit(lambda *xs: jax.lax.map(lambda x: _eso_routes(*x), xs))(
        plant, jnp.asarray(np.concatenate([fac, np.ones((1, 4))])),
        jnp.asarray(np.append(w0, w)), jnp.asarray(np.concatenate([i0, np.asarray(i)[None]])),
        jnp.asarray(np.append(a, obs.a)))
    ge, eso = (jax.tree_util.tree_map(np.asarray, r) for r in (ge, eso))
    return ge, eso, a


def test_generic_route_agrees_with_the_eso_reduction_under_mismatch_and_fal(eso_routes):
    """With observer-model mismatch (all four parameters) and fal feedback the closed form
    does not apply; the zhang2022-specific reduction (`eso_equilibria`) and the generic
    route must find the same equilibria and stability."""
    ge, eso, a = eso_routes
    ge, eso = (jax.tree_util.tree_map(lambda v: v[:-1], r) for r in (ge, eso))
    ok = (ge.status >= 0) & (eso.status >= 0)
    lin = a == 1.0
    # linear feedback: the generic route always resolves; fal's kinks (slope jumps at
    # |e| = eta) can stall its inner Gauss-Newton steps, which it reports as degenerate
    # (that is why `equilibria(method="auto")` takes zhang2022's reduction for fal)
    assert ok[lin].mean() > 0.999 and ok[~lin].mean() > 0.9
    assert np.all(eso.status >= 0)
    same = (ge.status == eso.status) & (ge.n == eso.n)
    assert np.all(same[ok & lin])
    assert same[ok & ~lin].mean() > 0.99  # fal: a close pair may hide in a stalled cell
    K = 4
    sel = ok & same
    for f in ("theta", "stable"):
        x = np.nan_to_num(getattr(ge, f)[sel][:, :K].astype(float), nan=9.0)
        y = np.nan_to_num(getattr(eso, f)[sel][:, :K].astype(float), nan=9.0)
        np.testing.assert_allclose(x, y, atol=1e-7)
    assert np.sum(eso.status == 2) > 0  # "no equilibrium" occurs


def test_auto_method_takes_the_eso_reduction_for_fal(eso_routes):
    m = SALIENT.three_phase_motor
    obs = make_observer("eso", SALIENT)
    w, i = _op(SALIENT)
    auto = analysis.equilibria(obs, m, w, i)
    ref = analysis.eso_equilibria(w, i, obs.linear_gains(w, i), m, m, a=obs.a, eta=obs.eta)
    np.testing.assert_array_equal(np.asarray(auto.theta), np.asarray(ref.theta))
    # the generic route (`equilibria(method="generic")`'s body) for this observer: the
    # last point of `eso_routes`
    gen = jax.tree_util.tree_map(lambda v: v[-1], eso_routes[0])
    np.testing.assert_allclose(gen.theta[gen.valid],
                               np.asarray(ref.theta)[np.asarray(ref.valid)], atol=1e-8)


def test_fig9_equilibrium_by_the_generic_route():
    """zhang2022 Fig. 9's design on Table I: the nonzero equilibrium at
    2 atan(w1 / (2 zeta1 w0)) = 53.13 deg at no load, unstable."""
    m = DRIVE.three_phase_motor
    obs = pj.LESOObserver(m, pj.ESODesign.fixed_ratio(0.5, 0.5))
    eq = analysis.equilibria(obs, m, 0.2 * DRIVE.w_rated, (0.0, 0.0))
    th = np.degrees(np.asarray(eq.theta)[np.asarray(eq.valid)])
    assert int(eq.status) == 0 and len(th) == 2
    np.testing.assert_allclose(th[1], math.degrees(2 * math.atan(0.5 / (2 * 0.5))), atol=1e-8)
    assert not bool(np.asarray(eq.stable)[np.asarray(eq.valid)][1])


def test_statuses_under_vmap_never_nan_or_raise():
    """Standstill is degenerate for zhang2022's design, a large resistance error at low
    speed leaves no equilibrium; both are statuses, under vmap, with no NaN elsewhere."""
    m = DRIVE.three_phase_motor
    obs = make_observer("leso", DRIVE)
    mh = pj.PMSMParams(R_s=3.0 * m.R_s, L_d=m.L_d, L_q=m.L_q, psi_f=m.psi_f, n_p=m.n_p)

    def one(w, k):
        o = obs.with_motor(jax.tree_util.tree_map(lambda a, b: a + k * (b - a), m, mh))
        return analysis.classify(o, m, w, jnp.array([0.0, 2.0 * DRIVE.base.I_b]))

    w = jnp.array([0.0, 0.5, 0.01, 0.5]) * DRIVE.w_rated
    k = jnp.array([0.0, 0.0, 1.0, 0.025])
    c = jax.jit(jax.vmap(one))(w, k)
    st = np.asarray(c.status)
    assert st[0] == -1 and st[1] == 0 and st[2] == 2 and st[3] == 0, st
    assert np.isfinite(np.asarray(c.principal_theta)[3])
    assert abs(float(c.principal_theta[3])) > 1e-3  # the resistance error shifts it
    assert np.all(np.isnan(np.asarray(c.principal_theta)[:1]))


# the salient machine of the design maps below, and the LESO's error dynamics on it as a
# function of plain numbers (one compiled program for every design, model and point)
MAP_DRIVE = pj.replace_params(DRIVE, L_d=1e-3, L_q=12e-3)


def _leso_rhs(x, w2, zeta2, L_q_hat, w_m, i_dq):
    obs = make_observer("leso", MAP_DRIVE, w2=w2, zeta2=zeta2).with_motor(
        pj.replace_params(MAP_DRIVE, L_q=L_q_hat).three_phase_motor)
    return obs.error_rhs(x, OperatingPoint(w_m, i_dq), MAP_DRIVE.three_phase_motor)


_RHS = jax.jit(_leso_rhs)
_JAC = jax.jit(jax.jacfwd(_leso_rhs))


def _classify_by_scipy(L_q_hat, speed_pu, i_dq_pu, w2, zeta2):
    """Feasibility of the LESO on `MAP_DRIVE` (observer model: its L_q replaced by
    `L_q_hat`, design `w2`, `zeta2`) at one operating point by an independent route:
    every equilibrium of its error dynamics (`error_rhs`) by SciPy's `fsolve` (with the
    forward-mode Jacobian) from 36 starting angles, merged where the angles agree; the
    stability of each from the eigenvalues of its Jacobian by central differences
    (NumPy). Status as `analysis.classify`: 2 no equilibrium, 1 a stable one besides the
    principal one (the one closest to angle 0), else 0."""
    import scipy.optimize

    w_m = speed_pu * float(MAP_DRIVE.w_rated)
    i_dq = np.asarray(i_dq_pu) * float(MAP_DRIVE.base.I_b)
    args = (w2, zeta2, L_q_hat, w_m, i_dq)
    obs = make_observer("leso", MAP_DRIVE, w2=w2, zeta2=zeta2)
    sc = np.asarray(obs.error_scale(OperatingPoint(w_m, i_dq), MAP_DRIVE.three_phase_motor))
    f = lambda x: np.asarray(_RHS(x, *args))  # noqa: E731
    F = lambda z: f(z * sc) / (sc * abs(w_m))  # noqa: E731
    Fp = lambda z: np.asarray(_JAC(z * sc, *args)) * sc / (sc[:, None] * abs(w_m))  # noqa
    ia = obs.coordinates.angle
    roots = []
    for th in np.linspace(-math.pi, math.pi, 37)[:-1] + 0.02:
        z0 = np.zeros(4)
        z0[ia] = th / sc[ia]
        z = scipy.optimize.fsolve(F, z0, fprime=Fp, xtol=1e-13, full_output=True)[0]
        if np.max(np.abs(F(z))) < 1e-9:
            x = z * sc
            x[ia] = math.remainder(x[ia], 2 * math.pi)
            if all(abs(math.remainder(x[ia] - r[ia], 2 * math.pi)) > 1e-6 for r in roots):
                roots.append(x)
    if not roots:
        return {"status": 2, "n_nonzero": 0, "stable_theta_deg": math.nan}
    stable = []
    for x in roots:
        J = np.stack([(f(x + e) - f(x - e)) / (2 * e[j])
                      for j, e in enumerate(np.diag(1e-7 * sc))], 1)
        stable.append(np.linalg.eigvals(J).real.max() < 0)
    k0 = int(np.argmin([abs(x[ia]) for x in roots]))  # the principal equilibrium
    other = [x[ia] for k, x in enumerate(roots) if k != k0 and stable[k]]
    return {"status": int(bool(other)), "n_nonzero": len(roots) - 1,
            "stable_theta_deg": (math.degrees(min(other, key=abs)) if other else math.nan)}

def test_design_map_over_any_two_parameters_matches_the_closed_form():
    drive = MAP_DRIVE
    obs = make_observer("leso", drive)
    z, r = np.linspace(0.3, 3.0, 4), np.linspace(0.3, 2.0, 3)
    kw = dict(i_dq=(0.0, 2.0))
    fast = analysis.design_map(obs, drive, [0.2], ("zeta1", z), ("ratio", r), **kw)
    old = analysis.feasibility_map(drive, [0.2], z, r, **kw)
    assert fast.method == "closed_form"
    np.testing.assert_array_equal(np.asarray(old.status), np.asarray(fast.status))
    assert np.any(np.asarray(fast.status) == 1) and np.any(np.asarray(fast.status) == 0)
    # the generic route's map against the closed form, on the same salient machine and
    # current (other axes: w2 x zeta2): notebooks/03_feasibility_and_convergence.ipynb,
    # section 3, asserts that they are equal; the classification itself against the
    # quartic: test_generic_route_agrees_with_the_quartic_on_2500_designs
    # axes that are not zhang2022's: bandwidth x damping of the speed loop, with mismatch,
    # every status against an independent classification (`_classify_by_scipy`)
    w2s, z2s = [100.0, 300.0], [0.2, 1.5]
    for L_q, want in ((9e-3, [[0, 1], [0, 1]]), (14e-3, [[2, 2], [2, 2]])):
        m_hat = pj.replace_params(drive, L_q=L_q).three_phase_motor
        mism = obs.with_motor(m_hat)
        other = analysis.design_map(mism, drive, [0.3], ("w2", w2s),
                                    ("zeta2", z2s), **kw)
        assert other.method == "generic" and other.x_name == "w2"
        st = np.asarray(other.status)[0, 0]
        assert st.tolist() == want  # (w2, zeta2): the damping decides, not w2
        for a, w2 in enumerate(w2s):
            for b, z2 in enumerate(z2s):
                ref = _classify_by_scipy(L_q, 0.3, (0.0, 2.0), w2, z2)
                assert st[a, b] == ref["status"], (L_q, w2, z2, ref)
                assert int(np.asarray(other.n_nonzero)[0, 0, a, b]) == ref["n_nonzero"]
                # measured: 1e-12 deg
                np.testing.assert_allclose(np.asarray(other.stable_theta_deg)[0, 0, a, b],
                                           ref["stable_theta_deg"], atol=1e-9,
                                           equal_nan=True)
    with pytest.raises(ValueError, match="no design parameter 'k1'.*w2"):
        analysis.design_map(obs, drive, [0.2], ("k1", z), ("ratio", r))
    with pytest.raises(ValueError, match="closed-form"):
        analysis.design_map(mism, drive, [0.2], ("zeta1", z), ("ratio", r),
                            plant=drive.three_phase_motor, method="closed_form")


def test_non_minimum_norm_gains_the_eso_reduction_declines_are_solved_generically():
    """zhang2022's reduction (`eso_equilibria`) needs kappa = 1 - u.JG1u/w0 > 0 (its
    scalar equation is then monotone); null-space components of (19) with zeta1 > 1 can
    make kappa <= 0, and it reports status -1 rather than guess. The generic route has no
    such condition: its equilibria are checked here against scipy's `fsolve` started
    from a dense grid of angles (an independent multi-start reference)."""
    from scipy.optimize import fsolve

    m = pj.replace_params(DRIVE, L_d=1.5e-3, L_q=4e-3).three_phase_motor
    design = pj.ESODesign.fixed_ratio(3.4265431030687195, 1.513093809771197,
                                      n2=2617.49948792537, n3=2610434.542726609)
    obs = pj.LESOObserver(m, design)
    w, i = 0.834268198709379 * DRIVE.w_rated, jnp.array([0.0, -13.50209198])
    assert int(analysis.eso_equilibria(w, i, obs.linear_gains(w, i), m).status) == -1
    eq = analysis.equilibria(obs, m, w, i)
    assert int(eq.status) == 0
    found = np.sort(np.asarray(eq.theta)[np.asarray(eq.valid)])
    op = OperatingPoint(w, i)
    D = np.asarray(obs.error_scale(op, m))
    f = jax.jit(lambda z: obs.error_rhs(z * D, op, m) / D / w)
    roots = []
    for th in np.linspace(-np.pi, np.pi, 73)[:-1]:
        z, info, ier, _ = fsolve(lambda z: np.asarray(f(jnp.asarray(z))),
                                 np.array([0.0, 0.0, th, 0.0]), full_output=True)
        if ier == 1 and np.max(np.abs(info["fvec"])) < 1e-10:
            t = (z[2] + np.pi) % (2 * np.pi) - np.pi
            if not any(abs(t - r) < 1e-6 for r in roots):
                roots.append(t)
    np.testing.assert_allclose(found, np.sort(roots), atol=1e-8)
