"""What the tuner's report says about a blocking validation run (`tuning.blocking`): its
noise floor and where in the run a design's change comes from, each checked against
`pmsmjax.simulate` run by run (not the tuner's batch) on a small problem."""

import jax.random as jr
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from tuning.blocking import NOISE_FLOOR_STREAM, PHASES, noise_floor, phase_split
from tuning.scenarios import observer_model, scenario


P = tg.TuningProblem.quick()
RUNS = [0, 3]


def _errors_one_by_one(p, space, sset, j, x=None, key=None):
    """Run `j` of `sset` with design `x` (None: the paper's) through `pmsmjax.simulate`
    alone: its sample times (s) and angle error (deg), optionally with another noise
    `key`."""
    drive, foc = p.drive(), p.controller()
    motor = observer_model(drive, *(float(getattr(sset, k)[j])
                                    for k in ("k_d", "k_q", "k_R", "k_psi")))
    sc = scenario(drive, sset.s0[j], sset.s1[j], sset.t0[j], sset.t1[j], sset.t_load[j],
                  sset.load_pu[j], sset.t_end)
    tr = pj.simulate(drive, foc, space.observer(x, motor), sc, T_s=p.T_s,
                     sensing=pj.Sensing(noise_std=p.noise_std * float(sset.k_noise[j])),
                     key=sset.keys[j] if key is None else key, theta0=0.0,
                     w_m0=float(sset.s0[j]) * float(drive.w_rated), theta_hat0=0.0,
                     save_every=p.save_every, throw=False)
    return np.asarray(tr.t), np.asarray(pj.run_errors(tr)[0])


def test_phase_split_adds_up_and_matches_single_runs():
    """Each phase's RMS is that of a single `pmsmjax.simulate` run over the phase's
    samples (by the scenario's times); the phases' mean squares weighted by their samples
    add up to the run's, which is the tuner's `rms_deg` metric; the shares of the change
    add up to 100 %."""
    space = tg.DesignSpace(P)
    vset = tg.validation_set(P)
    x = np.asarray(space.paper_point()) * np.array([1.6, 0.7, 1.2, 1.3])
    rows = phase_split(P, space, vset, RUNS, x)
    ev = tg.Evaluator(P, space, vset)
    rms = {"paper": np.asarray(ev.reference.rms_deg), "tuned": np.asarray(ev.metrics(x).rms_deg)}
    for j, row in zip(RUNS, rows):
        assert row["run"] == j and list(row["phases"]) == list(PHASES)
        bounds = [0.0, float(vset.t0[j]), float(vset.t1[j]), float(vset.t_load[j]), np.inf]
        for name, design in (("paper", None), ("tuned", x)):
            t, e = _errors_one_by_one(P, space, vset, j, design)
            np.testing.assert_allclose(row["rms_deg"][name], np.sqrt(np.mean(e ** 2)),
                                       rtol=1e-9)
            np.testing.assert_allclose(row["rms_deg"][name], rms[name][j], rtol=1e-9)
            total = 0.0
            for p, ph in enumerate(PHASES):
                sel = (t >= bounds[p]) & (t < bounds[p + 1])
                got = row["phases"][ph]
                np.testing.assert_allclose(got["samples_pct"], 100 * sel.mean(), rtol=1e-12)
                np.testing.assert_allclose(got["rms_deg"][name],
                                           np.sqrt(np.mean(e[sel] ** 2)), rtol=1e-9)
                total += got["samples_pct"] / 100 * got["rms_deg"][name] ** 2
            np.testing.assert_allclose(total, row["rms_deg"][name] ** 2, rtol=1e-9)
        shares = [row["phases"][ph]["share_of_change_pct"] for ph in PHASES]
        np.testing.assert_allclose(sum(shares), 100.0, rtol=1e-9)


def test_noise_floor_against_single_runs_and_zero_without_noise():
    """The noise floor is the largest relative change of the paper design's RMS over the
    other noise realisations, each run by itself through `pmsmjax.simulate` with that
    key; without current noise every realisation is the same run and the floor is 0."""
    space = tg.DesignSpace(P)
    vset = tg.validation_set(P)
    n_keys = 2
    floor = noise_floor(P, space, vset, RUNS, n_keys=n_keys)
    others = jr.split(jr.fold_in(jr.PRNGKey(P.seed), NOISE_FLOOR_STREAM),
                      n_keys * len(RUNS))
    for i, j in enumerate(RUNS):
        rms0 = np.sqrt(np.mean(_errors_one_by_one(P, space, vset, j)[1] ** 2))
        rel = [np.sqrt(np.mean(_errors_one_by_one(
            P, space, vset, j, key=others[r * len(RUNS) + i])[1] ** 2)) / rms0 - 1
            for r in range(n_keys)]
        np.testing.assert_allclose(floor[i], np.max(np.abs(rel)), rtol=1e-7, atol=1e-12)
        assert floor[i] > 1e-4  # the noise moves every run's RMS
    quiet = P.replace(noise_std=0.0)
    np.testing.assert_array_equal(
        noise_floor(quiet, tg.DesignSpace(quiet), tg.validation_set(quiet), RUNS,
                    n_keys=n_keys), 0.0)
    with pytest.raises(ValueError, match="n_keys"):
        noise_floor(P, space, vset, RUNS, n_keys=0)


def test_blocking_runs_carry_their_floor_and_phases():
    """A design made to fail the rule (an RMS 50 % above the paper's on one run): its
    blocking run's record has the noise floor and the phase split, and the verdict says
    how many of the blocking runs lie within their floor."""
    from tuning.pipeline import _blocking

    space = tg.DesignSpace(P)
    vset = tg.validation_set(P)
    ones = np.ones(vset.n)
    rms = np.where(np.arange(vset.n) == 1, 1.5, 1.0)

    def metrics(r):
        z = np.zeros(vset.n)
        return tg.Metrics(rms_deg=r, peak_deg=z, static_deg=z, noise_rad_s=z,
                          out_of_lock=z, lost_lock=z.astype(bool), ok=ones.astype(bool),
                          loss=ones)

    verdict = {"where_not": []}
    x = np.asarray(space.paper_point()) * np.array([1.6, 0.7, 1.2, 1.3])
    _blocking(P, vset, {"tuned": metrics(rms), "paper": metrics(ones)}, verdict,
              lambda *a: None, np.zeros(vset.n, bool), space=space, x=x)
    (r,) = verdict["blocking_runs"]
    assert r["run"] == 1 and r["rms_change_pct"] == pytest.approx(50.0)
    np.testing.assert_allclose(r["noise_floor_pct"],
                               100 * noise_floor(P, space, vset, [1])[0], rtol=1e-12)
    assert list(r["phases"]) == list(PHASES)
    assert (f"is {r['noise_floor_pct']:.1f} %: 0 of 1 runs' RMS change lies within it"
            in verdict["where_not"][-1]), verdict["where_not"][-1]  # one run: one number
