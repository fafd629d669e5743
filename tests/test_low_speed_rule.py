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


def test_blocking_runs_reuse_the_rules_sensored_records():
    """Where the rule measured every run, the blocking runs' report takes its records
    instead of simulating them again: the same numbers as measured afresh (a run worse by
    more than the tolerance at +0.4 p.u., kept by the rule, and one at +0.1 p.u., beyond
    it, which is not a blocking run)."""
    from tuning.pipeline import _blocking
    from tuning.scenarios import _low_speed

    p = tg.TuningProblem(observer="c-leso", val_speeds_pu=(0.1, 0.4),
                         val_cases=tg.VALIDATION_CASES[:1])
    vset = tg.validation_set(p)
    beyond, _, records = _low_speed(p, vset)
    s1 = np.asarray(vset.s1)
    ones = np.ones(vset.n)
    rms = np.where(np.isclose(s1, 0.4) | np.isclose(s1, 0.1), 1.5, 1.0)  # +50 %

    def metrics(r):
        z = np.zeros(vset.n)
        return tg.Metrics(rms_deg=r, peak_deg=z, static_deg=z, noise_rad_s=z,
                          out_of_lock=z, lost_lock=z.astype(bool), ok=ones.astype(bool),
                          loss=ones)

    m = {"tuned": metrics(rms), "paper": metrics(ones)}
    reused, fresh = {"where_not": []}, {"where_not": []}
    _blocking(p, vset, m, reused, lambda *a: None, beyond, records)
    _blocking(p, vset, m, fresh, lambda *a: None, beyond)
    assert [r["run"] for r in reused["blocking_runs"]] == [int(np.argmax(np.isclose(s1, 0.4)))]
    assert reused["where_not"] == fresh["where_not"]
    for a, b in zip(reused["blocking_runs"], fresh["blocking_runs"]):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_allclose(a[k], b[k], rtol=1e-9)
