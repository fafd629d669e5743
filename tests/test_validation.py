"""The tuner's validation runs (`tuning.validation`): closed-loop, speed-controlled
sensorless runs that differ from the training scenarios, and their metrics against a
direct `pmsmjax.simulate` of the same run."""

import math

import jax
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from tuning.validation import observer_model


CFG = tg.TuningConfig.quick()


def test_validation_scenarios_differ_from_training():
    cfg = tg.TuningConfig()
    v = tg.validation_scenarios(cfg)
    rows = v.table()
    assert v.n == 2 * len(cfg.val_speeds_pu) * len(cfg.val_cases)
    speeds = {r["speed_pu"] for r in rows}
    # both directions, and no final speed is a training speed
    assert speeds == {s * sign for s in cfg.val_speeds_pu for sign in (1, -1)}
    assert not {abs(s) for s in speeds} & set(cfg.speeds_pu)
    # every machine parameter of the observer's model is wrong in some run, and the
    # noise is raised in some
    for k in ("k_d", "k_q", "k_R", "k_psi", "k_noise"):
        assert any(r[k] > 1 for r in rows) and (k == "k_noise" or any(r[k] < 1 for r in rows))
    # other noise keys than training and held-out
    keys = {tuple(np.asarray(k).tolist()) for k in v.keys}
    for scen in (tg.training_scenarios(cfg), tg.heldout_scenarios(cfg)):
        assert not keys & {tuple(np.asarray(k).tolist()) for k in scen.keys}


def test_validation_runs_are_closed_loop_and_match_a_direct_simulation():
    """The runs are speed controlled (nothing imposed): the rotor follows the ramp,
    dips at the load step and recovers, through the mechanics the simulation integrates;
    and `validate` equals a direct `pmsmjax.simulate` of one run."""
    cfg = CFG
    v = tg.validation_scenarios(cfg)
    sc = tg.validation_scenario(cfg, 0.5, 0.3, 0.4)
    assert sc.speed_mode and sc.w_m_imposed is None and sc.i_q_ref is None
    design = cfg.initial_schedule()
    traj = tg.simulate_validation(design, cfg, v, save_every=1)
    assert np.all(np.asarray(traj.ok))
    drive = cfg.drive()
    w_r = float(drive.w_rated)
    t = np.asarray(traj.t[0])
    t_step = 0.6 * cfg.val_t_end
    for j, row in enumerate(v.table()):
        w = np.asarray(traj.w_m[j]) / w_r
        s = row["speed_pu"]
        # starts at the ramp's start speed, is near the final speed before the step
        assert w[0] == pytest.approx(row["start_pu"], rel=1e-9)
        before = w[(t > t_step - 0.05) & (t < t_step)]
        assert np.all(np.abs(before - s) < 0.1 * abs(s))
        # the braking load step slows the rotor (in its direction of rotation) ...
        after = w[t >= t_step]
        dip = np.max(np.sign(s) * (s - after))
        assert dip > 0.01 * abs(s)
        # ... which a speed-imposed run could not do; the speed loop brings it back
        assert abs(after[-1] - s) < 0.5 * dip
        # the rotor speed obeys the mechanics: J/n_p dw/dt = tau_M - tau_L - friction
        J, n_p = float(drive.mechanics.J), float(drive.motor.n_p)
        dw = np.diff(np.asarray(traj.w_m[j])) / cfg.T_s
        tau = np.asarray(traj.tau_M[j]) - np.asarray(traj.tau_L[j])
        k = (t[:-1] > 0.02) & (np.abs(t[:-1] - t_step) > 2 * cfg.T_s)
        resid = J / n_p * dw[k] - 0.5 * (tau[:-1] + tau[1:])[k]
        assert np.median(np.abs(resid)) < 0.05 * float(drive.tau_rated)

    # one run directly through pmsmjax.simulate gives the same metrics
    j = 3
    row = v.table()[j]
    obs = tg.make_observer(cfg.observer, drive, design,
                           motor=observer_model(drive, row["k_d"], row["k_q"], row["k_R"],
                                                row["k_psi"]))
    direct = pj.simulate(drive, cfg.controller(), obs,
                         tg.validation_scenario(cfg, row["speed_pu"], row["start_pu"],
                                                row["load_pu"]),
                         T_s=cfg.T_s, sensing=pj.Sensing(noise_std=cfg.noise_std
                                                         * row["k_noise"]),
                         key=v.keys[j], w_m0=row["start_pu"] * w_r, theta_hat0=0.0,
                         save_every=cfg.save_every)
    m_direct = tg.validation_metrics(jax.tree_util.tree_map(lambda a: a[None], direct), cfg)
    m = tg.validate(design, cfg, v)
    for f in ("loss", "pos_rms_deg", "theta_ss_deg", "noise_rad_s"):
        assert float(getattr(m, f)[j]) == pytest.approx(float(getattr(m_direct, f)[0]),
                                                        rel=1e-9, abs=1e-12), f
    # the static error is the mean angle error over the last 20 % of the run
    th = np.degrees(np.asarray(direct.theta_err))
    tt = np.asarray(direct.t)
    last = th[tt >= 0.8 * cfg.val_t_end - 0.5 * cfg.T_s]
    assert float(m.theta_ss_deg[j]) == pytest.approx(last.mean(), rel=1e-9)
    assert float(m.pos_rms_deg[j]) == pytest.approx(math.sqrt(np.mean(th ** 2)), rel=1e-6)


@pytest.mark.parametrize("kwargs, fragment", [
    (dict(val_speeds_pu=(0.0, 0.5)), "val_speeds_pu"),
    (dict(val_cases=((1.0, 1.0, -1.0, 1.0, 1.0),)), "val_cases"),
    (dict(val_t_end=0.30013), "val_t_end"),
    (dict(val_load_pu=50.0), "val_load_pu"),
])
def test_bad_validation_config_raises(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        tg.TuningConfig.quick(**kwargs)
