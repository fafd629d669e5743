"""Gain tuning (`tuning`): parametrisation, gradients against finite differences, a small
tuning run against the paper's design, feasibility, serialisation and bad input.

The configurations are tiny (`TuningConfig.quick`: 4 training runs of 0.1 s at 4 kHz), so
most of the time goes into compiling the batched simulation and its gradient.
"""

import json
import math

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from pmsmjax.analysis import classify_designs, eso_equilibria
from tuning.__main__ import build_parser, main


QUICK = tg.TuningConfig.quick()


# ---------------------------------------------------------------------------------------
# Parametrisation
# ---------------------------------------------------------------------------------------

def test_paper_schedule_is_zhang38():
    """All corrections 1 and nu = 0 give exactly the gains of `ESODesign.zhang38` (38)/(25),
    at any speed (inside and outside the nodes) and current, also the AFO's PI gains."""
    cfg = tg.TuningConfig()
    sched, paper = cfg.initial_schedule(), cfg.paper_design()
    motor = cfg.drive().three_phase_motor
    for w0 in (-700.0, 40.0, 251.3, 600.0, 1256.6, 2300.0):
        for i_dq in ((0.0, 0.0), (0.0, 2.9), (-1.0, 5.0)):
            i_dq = jnp.asarray(i_dq)
            a, b = sched(motor, w0, i_dq), paper(motor, w0, i_dq)
            for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
                np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-12)
            np.testing.assert_allclose(sched.pi(motor, w0, i_dq), paper.pi(motor, w0, i_dq),
                                       rtol=1e-13)


def test_parametrisation_round_trip_and_bounds():
    s_nodes = (0.2, 0.6, 1.0)
    values = dict(zeta1=[1.0, 2.0, 3.0], ratio=[0.5, 1.0, 2.0], zeta2=[0.7, 1.0, 2.0],
                  w2=[200.0, 300.0, 600.0], nu2=[-0.5, 0.0, 0.5], nu3=[0.3, 0.2, 0.1])
    sched = tg.GainSchedule.from_values(s_nodes, 1256.6, 314.16, values)
    got = sched.values(jnp.asarray(s_nodes))
    for name, v in values.items():
        np.testing.assert_allclose(got[name], v, rtol=1e-12, atol=1e-12)
    # between nodes: log-linear for the positive quantities, linear for nu
    mid = sched.values(0.4)
    f = sched.factors(0.4)
    assert mid["w2"] == pytest.approx(314.16 * f["w2"])
    assert mid["nu2"] == pytest.approx(-0.25)
    # any unconstrained value maps inside the box: positive, finite gains
    b = tg.Bounds()
    for z in (-50.0, -3.0, 0.0, 3.0, 50.0):
        for name in tg.TUNABLE:
            x = float(b.to_physical(name, jnp.asarray(z)))
            lo, hi = getattr(b, name)
            assert lo <= x <= hi and math.isfinite(x)
    with pytest.raises(ValueError, match="outside the open box"):
        tg.GainSchedule.from_values(s_nodes, 1256.6, 314.16, dict(w2=1e5))


def test_filter_spec_selects_the_tuned_leaves():
    sched = QUICK.initial_schedule()
    diff, static = eqx.partition(sched, tg.filter_spec(sched, ("w2", "zeta2")))
    assert diff.z_w2 is not None and diff.z_zeta2 is not None
    assert diff.z_zeta1 is None and diff.z_nu3 is None and diff.s_nodes is None
    assert static.z_w2 is None and static.z_zeta1 is not None
    assert len(jax.tree_util.tree_leaves(diff)) == 2
    assert eqx.tree_equal(eqx.combine(diff, static), sched)
    with pytest.raises(ValueError, match="non-empty subset"):
        tg.filter_spec(sched, ("w3",))
    with pytest.raises(ValueError, match="non-empty subset"):
        tg.filter_spec(sched, ())


# ---------------------------------------------------------------------------------------
# Bad configurations
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, fragment", [
    (dict(n_mismatch=0), "mismatch grid is empty"),
    (dict(mismatch_values=()), "mismatch grid is empty"),
    (dict(mismatch=(-0.5, 1.5)), "0 < lo <= hi"),
    (dict(mismatch_values=(0.5, -1.0)), "must be finite and > 0"),
    (dict(n_heldout=0), "held-out mismatch grid is empty"),
    (dict(n_mismatch=9), "shares values"),
    (dict(motor="nosuchmotor"), "Unknown motor 'nosuchmotor'"),
    (dict(bounds=dict(w2=(-2.0, 5.0))), "must satisfy 0 < lo < 1 < hi"),
    (dict(bounds=dict(nu2=(0.1, 1.0))), "must contain 0"),
    (dict(bounds=dict(w3=(0.5, 2.0))), "unknown quantity"),
    (dict(speeds_pu=(0.0, 0.5)), "must not contain 0"),
    (dict(speeds_pu=()), "is empty"),
    (dict(loads_pu=(5.0,)), "above the drive's limit"),
    (dict(t_transient=0.2, t_end=0.2), "t_transient"),
    (dict(observer="smo"), "must be one of eso, leso, afo"),
    (dict(tuned=("w2", "w3")), "distinct names"),
    (dict(T_s=-1e-4), "must be a finite number > 0"),
    (dict(save_every=7), "must divide the number of steps"),
])
def test_bad_config_raises(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        tg.TuningConfig.quick(**kwargs)


def test_bounds_and_scenarios_reject_bad_input():
    with pytest.raises(ValueError, match="0 < lo < 1 < hi"):
        tg.Bounds(zeta1=(-1.0, 2.0))
    with pytest.raises(ValueError, match="pair"):
        tg.Bounds(w2=(1.0,))
    with pytest.raises(ValueError, match="empty"):
        tg.make_scenarios([], [0.5], [0.0])
    with pytest.raises(ValueError, match="> 0"):
        tg.make_scenarios([0.0, 1.0], [0.5], [0.0])


def test_cli_help_and_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for opt in ("--out", "--motor", "--quick", "--optimiser", "--mismatch", "--steps",
                "--seed", "--tune"):
        assert opt in out
    for action in build_parser()._actions:
        assert action.help, action.option_strings

    with pytest.raises(SystemExit) as e:
        main(["--motor", "nosuchmotor", "--out", str(tmp_path)])
    assert e.value.code == 2
    assert "invalid choice: 'nosuchmotor'" in capsys.readouterr().err

    for argv, fragment in ((["--n-mismatch", "0"], "mismatch grid is empty"),
                           (["--mismatch", "-1", "1.5"], "0 < lo <= hi"),
                           (["--tune", "w2,bogus"], "distinct names")):
        assert main(["--quick", "--out", str(tmp_path / "x"), *argv]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert err.startswith("python -m tuning: error:") and fragment in err
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------------------------------
# Gradients through the closed loop
# ---------------------------------------------------------------------------------------

def test_gradient_matches_central_differences():
    """d(loss)/d(each tunable leaf) by reverse mode through the whole batch of closed-loop
    simulations and the stability penalty, against central differences (float64).

    The point is moved away from the paper's design so that every term is generic. The
    equilibria that start the penalty's Newton steps are held fixed, so both derivatives
    see the same function. Measured agreement: 2e-7 relative with h = 1e-5; the
    truncation error is 2e-5 at h = 1e-4 and 2e-2 at h = 1e-3 (the penalty's softplus
    hinges are sharp). fal and the voltage limit have kinks, which a sample crossing
    within +-h would show as a larger error."""
    cfg = QUICK
    scen = tg.training_scenarios(cfg)
    sched = cfg.initial_schedule()
    diff, static = eqx.partition(sched, tg.filter_spec(sched, cfg.tuned))
    flat, unravel = jax.flatten_util.ravel_pytree(diff)
    flat = flat + 0.3 * jnp.sin(jnp.arange(flat.size) + 1.0)
    point = eqx.combine(unravel(flat), static)
    eqs = tg.equilibria(point, cfg, scen)

    def f(z):
        return tg.loss(eqx.combine(unravel(z), static), cfg, scen, eqs)[0]

    value, grad = jax.jit(jax.value_and_grad(f))(flat)
    f_jit = jax.jit(f)
    assert np.isfinite(value) and np.all(np.isfinite(grad))
    h = 1e-5
    fd = np.array([(f_jit(flat.at[i].add(h)) - f_jit(flat.at[i].add(-h))) / (2 * h)
                   for i in range(flat.size)])
    grad = np.asarray(grad)
    assert flat.size == len(cfg.tuned) * len(cfg.nodes_pu)
    scale = np.max(np.abs(grad))
    assert scale > 0
    np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-6 * scale)


# ---------------------------------------------------------------------------------------
# A small tuning run
# ---------------------------------------------------------------------------------------

def _check_feasible_with_analysis(design, cfg, scen, kind):
    """Independent check with `pmsmjax.analysis.eso_equilibria` (the general route of
    `classify_designs`): the designed equilibrium is stable, no other one is."""
    drive = cfg.drive()
    motor = drive.three_phase_motor
    for row in scen.table():
        mh = tg.observer_motor(drive, row["k_d"], row["k_q"])
        w0 = row["speed_pu"] * drive.w_rated
        i0 = jnp.array([0.0, row["load_pu"] * drive.tau_rated
                        / (drive.k_tau * motor.psi_f)])
        a, eta = (0.5, 0.05 * mh.psi_f) if kind == "eso" else (1.0, 1.0)
        eq = eso_equilibria(w0, i0, design(mh, w0, i0), motor, mh, a=a, eta=eta)
        assert int(eq.status) == 0, row
        p = int(eq.principal)
        assert bool(eq.stable[p]), row
        assert not np.any(np.asarray(eq.stable & eq.nonprincipal)), row
        assert abs(float(eq.theta[p])) < math.radians(20), row


def test_quick_tuning_beats_paper_design_is_feasible_and_reloads(tmp_path):
    cfg = QUICK
    report = tg.run_tuning(cfg, progress=False, log=None)
    L = report.losses
    # the tuned design beats (38)/(25) on the robust objective, in and out of training
    assert L["tuned"]["train"] < 0.95 * L["zhang38"]["train"]
    assert L["tuned"]["heldout"] < 0.95 * L["zhang38"]["heldout"]
    assert report.results["tuned"].stats["steps"] == cfg.steps
    hist = report.results["tuned"].stats["best"]
    assert np.all(np.diff(hist) <= 0) and hist[-1] == pytest.approx(L["tuned"]["train"])
    # feasible on every scenario (the report's exact check and an independent one)
    assert report.all_feasible("tuned")
    for scen in (report.train, report.heldout):
        _check_feasible_with_analysis(report.tuned, cfg, scen, cfg.observer)
    # the restricted (minimum-norm (25)) design with the analysis classifier
    mn = report.designs["min_norm_25"]
    drive = cfg.drive()
    motor = drive.three_phase_motor
    for row in report.train.table():
        mh = tg.observer_motor(drive, row["k_d"], row["k_q"])
        w0 = row["speed_pu"] * drive.w_rated
        v = mn.values(row["speed_pu"])
        assert float(v["nu2"]) == 0.0 and float(v["nu3"]) == 0.0
        i0 = jnp.array([0.0, row["load_pu"] * drive.tau_rated / (drive.k_tau * motor.psi_f)])
        c = classify_designs(motor, w0, i0, float(v["zeta1"]), float(v["ratio"]),
                             zeta2=float(v["zeta2"]), w2=float(v["w2"]), motor_hat=mh,
                             a=0.5, eta=0.05 * float(mh.psi_f), method="general")
        assert int(c.status) == 0 and bool(c.principal_stable), row

    # output files, required keys, and a bit-identical reload of the tuned schedule
    s = tg.write_report(report, tmp_path)
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert set(tg.REQUIRED_KEYS) <= set(saved)
    assert saved == s
    assert saved["feasible"] is True
    assert saved["tuned_loss"] == L["tuned"]["train"]
    assert len(saved["loss_history"]) == cfg.steps
    assert len(saved["scenarios"]["train"]) == report.train.n
    for name in ("loss_curve.png", "heatmaps.png", "time_trace.png", "tuned_schedule.eqx"):
        assert (tmp_path / name).stat().st_size > 0
    back = tg.load_schedule(tmp_path)
    la, ta = jax.tree_util.tree_flatten(report.tuned)
    lb, tb = jax.tree_util.tree_flatten(back)
    assert ta == tb
    for a, b in zip(la, lb):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()
    # and the reloaded design gives the same loss
    again, _ = tg.evaluate(back, cfg, report.train)
    assert float(again) == L["tuned"]["train"]


@pytest.mark.slow
@pytest.mark.parametrize("method, objective", [("bfgs", "robust"), ("lm", "average")])
def test_optimistix_optimisers_reduce_the_loss(method, objective):
    cfg = tg.TuningConfig.quick(optimiser=method, objective=objective, steps=6)
    scen = tg.training_scenarios(cfg)
    r = tg.optimise(cfg.initial_schedule(), cfg, scen, progress=False)
    base, _ = tg.evaluate(cfg.initial_schedule(), cfg, scen)
    assert r.loss < float(base)


def test_random_search_is_seeded():
    """Same seed, same designs and losses; the first design is the starting point."""
    cfg = tg.TuningConfig.quick()
    scen = tg.training_scenarios(cfg)
    s0 = cfg.initial_schedule()
    a = tg.random_search(s0, cfg, scen, n_designs=3, progress=False)
    b = tg.random_search(s0, cfg, scen, n_designs=3, progress=False)
    np.testing.assert_array_equal(a.stats["loss"], b.stats["loss"])
    base, _ = tg.evaluate(s0, cfg, scen)
    assert a.stats["loss"][0] == float(base)
    assert a.stats["n_simulations"].tolist() == [scen.n, 2 * scen.n, 3 * scen.n]
    assert pj.PRESET_NAMES  # the CLI's motor choices come from here
