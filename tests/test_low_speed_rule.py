"""The tuner's low-speed rule (`tuning.low_speed_runs`, `TuningProblem.low_speed_limit_pu`):
fixed before tuning, from a sensored drive of each validation run; checked on a small
case against `pmsmjax.simulate` run by run with the sensored observer."""

import numpy as np

import pmsmjax as pj
import tuning as tg
from tuning.scenarios import scenario


def test_the_rule_on_a_small_case():
    """li's drive, the nominal case at +-0.1 and +-0.4 p.u.: the load step takes the
    sensored drive to about 1 % of rated speed at +-0.1 p.u. (below the li observers'
    declared limit, 5 %) and nowhere near it at +-0.4 p.u. (its ramp starts at 0.24
    p.u.)."""
    p = tg.TuningProblem(observer="c-leso", val_speeds_pu=(0.1, 0.4),
                         val_cases=tg.VALIDATION_CASES[:1])
    vset = tg.validation_set(p)
    beyond, lowest = tg.low_speed_runs(p, vset)
    s1 = np.asarray(vset.s1)
    drive, foc = p.drive(), p.controller()
    w_r = float(drive.w_rated)
    ref = []
    for j in range(vset.n):  # one run at a time, not through the tuner's batch
        sc = scenario(drive, vset.s0[j], vset.s1[j], vset.t0[j], vset.t1[j],
                         vset.t_load[j], vset.load_pu[j], vset.t_end)
        tr = pj.simulate(drive, foc, pj.SensoredObserver(), sc, T_s=p.T_s,
                         sensing=pj.Sensing(noise_std=p.noise_std * float(vset.k_noise[j])),
                         key=vset.keys[j], theta0=0.0, w_m0=float(vset.s0[j]) * w_r,
                         theta_hat0=0.0, save_every=1, throw=False)
        ref.append(np.min(np.abs(np.asarray(tr.w_m))) / w_r)
    np.testing.assert_allclose(lowest, ref, rtol=1e-9)
    assert beyond.tolist() == (np.abs(s1) < 0.2).tolist(), (s1, lowest)
    assert np.all(lowest[np.abs(s1) < 0.2] < 0.02) and np.all(lowest[np.abs(s1) > 0.2] > 0.2)
    # an observer that declares no limit (the ESO): nothing simulated
    q = tg.TuningProblem(val_speeds_pu=(0.1, 0.4), val_cases=tg.VALIDATION_CASES[:1])
    none, nan = tg.low_speed_runs(q, tg.validation_set(q))
    assert not none.any() and np.all(np.isnan(nan))
