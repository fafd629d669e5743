"""The comparison job (`tuning.compare`, `python -m tuning compare`) on a tiny grid:
its metrics equal those of direct `simulate` calls, the metric definitions agree with a
NumPy re-implementation, every metric is finite or flagged, and an interrupted job
resumes to the same files."""

import json
import math
import re

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import pmsmjax as pj
from tuning.compare import (
    DESIGNS,
    CompareConfig,
    CompareInterrupted,
    aggregate,
    lock_comparison,
    markdown,
    run_comparison,
    tuned_designs_from,
)
from tuning.compare.config import TRACE_SAMPLES
from tuning.compare.job import STOP_ENV, TIMING_KEYS
from tuning.compare.points import run_metrics
from tuning.scenarios import VAL_LOAD_STEP, VAL_RAMP, observer_model

from .helpers import lock_status_loop, read_npz


OBSERVER = "parallel-model"


def tiny(**kw):
    base = dict(observers=(OBSERVER,), T_s=250e-6, t_end=0.1, speeds_pu=(0.5,),
                loads_pu=(0.0, 1.0), cases=((1.0, 1.0, 1.0, 1.0), (0.7, 1.3, 1.5, 0.9)),
                tune_steps=2, chunk_size=4, harmonic_speeds_pu=(0.5,))
    base.update(kw)
    return CompareConfig(**base)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare") / "job"
    config = tiny()
    # batch_size: bitwise the same results on any device count (the worker test below)
    summary = run_comparison(config, out, progress=False, log=None, batch_size=2)
    return config, out, summary


def _direct(config, sensored=False):
    """Every run of the grid with the paper design by direct `pmsmjax.simulate` calls
    (vmapped over points; the scenario built here from `pmsmjax.Scenario`; the observer in
    `pmsmjax.SpeedFromAngle` when the configuration asks for it). `sensored`: with the
    sensored observer instead, every sample kept."""
    drive = config.drive()
    foc = pj.FOC.from_drive(drive)
    w_r = float(drive.w_rated)
    q = lambda f: round(f * config.t_end / config.T_s) * config.T_s  # noqa: E731
    grid = config.grid()
    n = len(grid["case"])
    cases = np.asarray(config.cases)[grid["case"]]

    def one(j, speed, load, k):
        obs = pj.observers.make_observer(
            OBSERVER, drive, motor=observer_model(drive, k[0], k[1], k[2], k[3]))
        if sensored:
            obs = pj.SensoredObserver()
        elif config.speed_from_angle is not None:
            obs = pj.SpeedFromAngle(obs, w_track=2 * math.pi * config.speed_from_angle)
        tau = load * float(drive.tau_rated) * jnp.sign(speed)
        sc = pj.Scenario(t_end=config.t_end,
                         w_m_ref=pj.Profile([q(VAL_RAMP[0]), q(VAL_RAMP[1])],
                                            jnp.stack([config.start_frac * speed * w_r,
                                                       speed * w_r])),
                         tau_L=pj.Profile([q(VAL_LOAD_STEP)] * 2, jnp.stack([0 * tau, tau])))
        key = jr.fold_in(jr.PRNGKey(config.seed), j.astype(jnp.uint32))
        return pj.simulate(drive, foc, obs, sc, T_s=config.T_s,
                           sensing=pj.Sensing(noise_std=config.noise_std), key=key,
                           theta0=0.0, w_m0=config.start_frac * speed * float(drive.w_rated),
                           theta_hat0=0.0, save_every=1 if sensored else config.save_every,
                           throw=False)

    return grid, jax.jit(jax.vmap(one))(jnp.arange(n), jnp.asarray(grid["speed_pu"]),
                                        jnp.asarray(grid["load_pu"]), jnp.asarray(cases))


def test_metrics_equal_direct_simulate(job):
    config, out, summary = job
    grid, traj = _direct(config)
    # compiled, as the job runs it (op by op each small operation compiles on its own)
    metrics = jax.jit(lambda tr: run_metrics(tr, config))(traj)
    runs = {k: np.asarray(v) for k, v in metrics.items()}
    feas = read_npz(out / "sweeps" / OBSERVER / "paper" / "analysis" / "result.npz")
    want = aggregate(runs, feas, config, grid)
    got = summary["observers"][OBSERVER]["designs"]["paper"]
    for k, v in want.items():
        if isinstance(v, float):
            assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
        elif k != "flags":
            assert got[k] == v, k
    # the sweep's per-run outputs are the direct runs'
    res = read_npz(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz")
    np.testing.assert_allclose(res["static_deg"].reshape(-1), runs["static_deg"],
                               rtol=1e-9, atol=1e-12)

    # the definitions, independently, in NumPy: static error and speed noise over the
    # static window (the last 20 % of the run, by time), RMS, settling and loss of lock
    t = np.asarray(traj.t)
    th = np.degrees(np.asarray(traj.theta_err))
    w_err = np.asarray(traj.w_m - traj.w_hat)
    for j in range(th.shape[0]):
        win = t[j] >= 0.8 * config.t_end - 1e-9
        assert runs["static_deg"][j] == pytest.approx(th[j][win].mean(), rel=1e-9, abs=1e-9)
        assert runs["noise_rad_s"][j] == pytest.approx(w_err[j][win].std(), rel=1e-6,
                                                       abs=1e-6)
        assert runs["rms_deg"][j] == pytest.approx(np.sqrt(np.mean(th[j] ** 2)), rel=1e-9)
        t0 = VAL_RAMP[0] * config.t_end
        outside = np.nonzero((t[j] >= t0 - 1e-9)
                             & (np.abs(th[j] - runs["static_deg"][j])
                                > config.settle_band_deg))[0]
        if outside.size == 0:
            settle = 0.0
        elif outside[-1] == t.shape[-1] - 1:
            settle = math.nan  # never settled
        else:
            settle = t[j][outside[-1] + 1] - t0
        assert runs["settle_s"][j] == pytest.approx(settle, abs=1e-12, nan_ok=True)
        ref = lock_status_loop(t[j], np.asarray(traj.theta_err)[j],
                               ok=bool(np.asarray(traj.ok)[j]), lock_deg=config.lock_deg,
                               start_locked=True)
        assert bool(runs["lost_lock"][j]) == ref[2]
    # the tiny grid is not trivial: the mismatched case moves the static error
    assert np.ptp(runs["static_deg"]) > 0.1


def _finite_or_flagged(m, where):
    for k, v in m.items():
        if k in ("flags", "lost_lock_where"):
            continue
        if v is None:
            assert k in m.get("flags", {}) or "all" in m.get("flags", {}), (where, k)
        elif isinstance(v, float | int):
            assert math.isfinite(v), (where, k)


def test_every_metric_finite_or_flagged(job):
    config, out, summary = job
    s = json.loads((out / "comparison.json").read_text())  # strict JSON: no NaN
    assert set(s["observers"]) == {OBSERVER}
    for name, e in s["observers"].items():
        assert set(e["designs"]) == set(DESIGNS)
        for d, m in e["designs"].items():
            _finite_or_flagged(m, (name, d))
        assert e["observer_us_per_step"] > 0
    # the harmonic sensitivity of the paper design: the parallel-model observer's
    # linearisation is stable at 0.5 p.u., so it is computed (not flagged), and it is the
    # largest ripple of `pmsmjax.analysis.harmonic_ripple` called here directly
    m = s["observers"][OBSERVER]["designs"]["paper"]
    assert "harmonic_deg_per_pct" not in m.get("flags", {})
    drive = config.drive()
    obs = pj.observers.make_observer(OBSERVER, drive)
    want = max(float(np.max(np.abs(np.asarray(pj.analysis.harmonic_ripple(
        obs, drive, pj.analysis.OperatingPoint(sp * float(drive.w_rated), jnp.zeros(2)),
        jnp.asarray(config.harmonic_orders))))))
        for sp in config.harmonic_speeds_pu)
    assert m["harmonic_deg_per_pct"] == pytest.approx(want, rel=1e-9)
    md = (out / "comparison.md").read_text()
    assert md.count(f"| {OBSERVER} |") == 2


def _where(speed, load, k=(1.0, 1.0, 1.0, 1.0), feasible=None, status=None, t=0.02,
           phase="ramp"):
    w = dict(speed_pu=speed, load_pu=load, k_d=k[0], k_q=k[1], k_R=k[2], k_psi=k[3],
             t_lost_s=t, phase=phase)
    if feasible is not None:
        w["feasible"] = feasible
    if status is not None:
        w["analysis_status"] = status
    return w


def _entry(paper, tuned):
    return {"designs": {"paper": dict(lost_lock=len(paper), lost_lock_where=paper),
                        "tuned": dict(lost_lock=None if tuned is None else len(tuned),
                                      lost_lock_where=tuned or [])}}


def test_lock_comparison_accounting():
    """Hand-built cases of `lock_comparison`: fewer; not fewer, with each run lost only
    by the tuned design and its reason counted; none lost by either; none by the paper's
    design; no tuned design. And its section in comparison.md."""
    a, b = _where(0.1, 1.0), _where(-1.0, 0.0, (0.7, 1.3, 1.0, 1.0))
    c = _where(0.05, 1.0, (1.0, 1.0, 1.5, 1.0), feasible=False)
    d = _where(0.05, 0.0, feasible=True)
    r = lock_comparison(_entry([a, b], [a]))
    assert (r["paper"], r["tuned"], r["fewer"], r["why_not"]) == (2, 1, True, None)
    assert r["only_paper"] == [b] and r["only_tuned"] == []
    # the same grid point with the analysis's verdict attached is the same run
    r = lock_comparison(_entry([dict(a, feasible=True)], [a, c, d]))
    assert (r["paper"], r["tuned"], r["fewer"]) == (1, 3, False)
    assert r["only_tuned"] == [c, d] and r["only_paper"] == []
    assert r["why_not"] == ("2 runs lost only by the tuned design; 1 of them where the "
                            "analysis finds no stable designed equilibrium for it (it "
                            "cannot hold that point); 1 where it is feasible (lost on the "
                            "way, by phase: ramp 1)")
    # a point where the analysis failed (status -1) is infeasible by the map's count but
    # no physical verdict: counted and reported as a failure of the analysis, not as a
    # point the design cannot hold; status 2 (no equilibrium at all) is one it cannot
    e = _where(0.5, 1.0, (1.0, 1.3, 1.0, 1.0), feasible=False, status=-1)
    f = _where(0.1, 1.0, (1.0, 1.0, 1.5, 1.0), feasible=False, status=2)
    r = lock_comparison(_entry([], [e, f, dict(d, analysis_status=0)]))
    assert r["why_not"] == ("3 runs lost only by the tuned design; 1 of them where the "
                            "analysis finds no stable designed equilibrium for it (it "
                            "cannot hold that point); 1 where it is feasible (lost on the "
                            "way, by phase: ramp 1); 1 where the analysis "
                            "failed (status -1: no verdict); the paper's design loses none")
    # feasible points counted by the phase each was lost in
    g = _where(0.5, 0.0, feasible=True, status=0, t=0.07, phase="loaded")
    h = _where(1.0, 0.0, feasible=True, status=0, t=0.001, phase="start")
    assert lock_comparison(_entry([], [d, g, h]))["why_not"].endswith(
        "3 where it is feasible (lost on the way, by phase: start 1, ramp 1, loaded 1); "
        "the paper's design loses none")
    md = markdown(dict(motor="m", config=dict(noise_std=0.0, T_s=1e-4, t_end=0.1,
                                              settle_band_deg=2.0, lock_deg=45.0,
                                              harmonic_orders=[5], tuner="adam",
                                              tune_steps=2),
                       grid=dict(n_runs=4, speeds_pu=[0.1], loads_pu=[0.0], cases=[{}]),
                       skipped={}, observers={"x": dict(_entry([], [e]), lock_comparison=(
                           lock_comparison(_entry([], [e]))))}))
    assert ("  - 0.5 p.u., load 1, q 1.3; lost at 0.020 s (ramp); analysis: failed at this "
            "point (status -1): no verdict") in md.splitlines()
    r = lock_comparison(_entry([], []))
    assert not r["fewer"] and r["why_not"].startswith("neither design loses a run")
    r = lock_comparison(_entry([], [a]))
    assert r["why_not"] == ("1 run lost only by the tuned design; 1 without the analysis; "
                            "the paper's design loses none")
    assert lock_comparison(_entry([a], None)) is None
    summary = dict(motor="m", config=dict(noise_std=0.0, T_s=1e-4, t_end=0.1,
                                          settle_band_deg=2.0, lock_deg=45.0,
                                          harmonic_orders=[5], tuner="adam", tune_steps=2),
                   grid=dict(n_runs=4, speeds_pu=[0.1], loads_pu=[0.0], cases=[{}]),
                   skipped={}, observers={
                       "x": dict(_entry([a], [a, c, d]), lock_comparison=lock_comparison(
                           _entry([a], [a, c, d]))),
                       "y": dict(_entry([a, b], []), lock_comparison=lock_comparison(
                           _entry([a, b], [])))})
    md = markdown(summary)
    sec = md.split("## Lost lock: tuned against paper\n\n")[1].split("\n\n")[0].splitlines()
    assert sec[0].startswith("- x: paper 1, tuned 3: not fewer; 2 runs lost only")
    assert sec[1] == ("  - 0.05 p.u., load 1, R 1.5; lost at 0.020 s (ramp); analysis: no "
                      "stable designed equilibrium")
    assert sec[2] == "  - 0.05 p.u., load 0, matched; lost at 0.020 s (ramp); analysis: feasible"
    assert sec[3] == "- y: paper 2, tuned 0: fewer"


def test_lock_comparison_counts_the_runs_beyond_the_low_speed_limit_apart():
    """Hand-built cases of `lock_comparison` with the low-speed rule: the runs at its
    points are counted apart (`paper_within`, `tuned_within`), `fewer` compares the
    others, and a run lost only by the tuned design beyond the limit says so."""
    a, b = _where(0.1, 1.0), _where(-1.0, 0.0, (0.7, 1.3, 1.0, 1.0))
    c = _where(0.05, 1.0, (1.0, 1.0, 1.5, 1.0), feasible=False)
    d = _where(0.05, 0.0, feasible=True)
    pt = lambda w: (w["speed_pu"], w["load_pu"], w["k_d"], w["k_q"], w["k_R"],  # noqa: E731
                    w["k_psi"])
    low = dict(limit_pu=0.05, points={pt(c), (0.05, 0.5, 1.0, 1.0, 1.0, 1.0)})
    r = lock_comparison(_entry([a, b], [a, c, d]), low)
    assert (r["paper"], r["tuned"], r["paper_within"], r["tuned_within"]) == (2, 3, 2, 2)
    assert (r["beyond_limit"], r["low_speed_limit_pu"], r["fewer"]) == (2, 0.05, False)
    assert [w["beyond_limit"] for w in r["only_tuned"]] == [True, False]
    assert r["why_not"] == ("2 runs lost only by the tuned design; 1 of them beyond the "
                            "class's low-speed limit (0.05 p.u.: a sensored drive turns "
                            "slower there; counted apart); 1 where it is feasible (lost on "
                            "the way, by phase: ramp 1)")
    # with d beyond too, the tuned design loses fewer of the runs the rule judges
    r = lock_comparison(_entry([a, b], [a, c, d]), dict(low, points={pt(c), pt(d)}))
    assert (r["paper_within"], r["tuned_within"], r["fewer"], r["why_not"]) == (
        2, 1, True, None)
    r = lock_comparison(_entry([c], [c, d]), dict(low, points={pt(c), pt(d)}))
    assert r["why_not"] == ("neither design loses a run within the class's low-speed "
                            "limit: none to lose fewer of")
    # the same accounting without the rule is the one above
    assert lock_comparison(_entry([a, b], [a, c, d]))["tuned"] == 3
    md = markdown(dict(motor="m", config=dict(noise_std=0.0, T_s=1e-4, t_end=0.1,
                                              settle_band_deg=2.0, lock_deg=45.0,
                                              harmonic_orders=[5], tuner="adam",
                                              tune_steps=2),
                       grid=dict(n_runs=4, speeds_pu=[0.1], loads_pu=[0.0], cases=[{}]),
                       skipped={}, observers={"x": dict(
                           _entry([a, b], [a, c, d]),
                           lock_comparison=lock_comparison(_entry([a, b], [a, c, d]),
                                                           low))}))
    sec = md.split("## Lost lock: tuned against paper\n\n")[1].split("\n\n")[0].splitlines()
    assert sec[0].startswith("- x: paper 2, tuned 3 (within the class's low-speed limit "
                             "of 0.05 p.u., 2 grid runs beyond it counted apart: paper 2, "
                             "tuned 2): not fewer; 2 runs lost only")
    assert sec[1] == ("  - 0.05 p.u., load 1, R 1.5; lost at 0.020 s (ramp); beyond the "
                      "class's low-speed limit")


def test_low_speed_rule_on_the_grid(job, tmp_path, monkeypatch):
    """The job's low-speed rule: the sensored drive's lowest speed at every grid point
    (`sensored_point`, saved in `sweeps/sensored`) equals that of direct `simulate`
    calls with the sensored observer, and the lost-lock comparison counts the runs
    below the class's limit apart, as recounted here from both designs' saved runs. The
    class's declared limit is set here (the parallel-model estimator declares none)."""
    import shutil

    from pmsmjax.observers import observer_class

    config, out, _ = job
    part = tmp_path / "job"
    shutil.copytree(out, part)
    cls = observer_class(OBSERVER)
    monkeypatch.setattr(cls, "low_speed_limit_pu", 1e-6)
    run_comparison(config, part, progress=False, log=None, batch_size=2)
    sens = read_npz(part / "sweeps" / "sensored" / "runs" / "result.npz")
    lowest = sens["lowest_speed_pu"].reshape(-1)
    grid, traj = _direct(config, sensored=True)
    want = np.min(np.abs(np.asarray(traj.w_m)), axis=-1) / float(config.drive().w_rated)
    np.testing.assert_allclose(lowest, want, rtol=1e-9)
    c = json.loads((part / "comparison.json").read_text())["observers"][OBSERVER]
    assert c["lock_comparison"]["beyond_limit"] == 0
    # a limit between the measured lowest speeds: some runs beyond it, some not
    limit = float(np.median(lowest))
    assert np.any(lowest < limit) and np.any(lowest >= limit)
    monkeypatch.setattr(cls, "low_speed_limit_pu", limit)
    (part / "comparison.json").unlink()
    run_comparison(config, part, progress=False, log=None, batch_size=2)
    lc = json.loads((part / "comparison.json").read_text())["observers"][OBSERVER][
        "lock_comparison"]
    beyond = lowest < limit
    assert lc["beyond_limit"] == int(beyond.sum()) and lc["low_speed_limit_pu"] == limit
    within = {}
    for d in DESIGNS:
        r = read_npz(part / "sweeps" / OBSERVER / d / "runs" / "result.npz")
        within[d] = int(np.sum(r["lost_lock"].reshape(-1).astype(bool) & ~beyond))
    assert (lc["paper_within"], lc["tuned_within"]) == (within["paper"], within["tuned"])
    assert lc["fewer"] == (within["tuned"] < within["paper"])


def test_phase_at_the_scenario_times():
    """`tuning.scenarios.phase_at`: each phase begins at its time (inclusive)."""
    from tuning.scenarios import PHASES, phase_at

    times = (0.01, 0.03, 0.06)
    got = [phase_at(t, *times) for t in (0.0, 0.0099, 0.01, 0.0299, 0.03, 0.06, 0.1)]
    assert got == ["start", "start", "ramp", "ramp", "steady", "loaded", "loaded"]
    assert set(got) == set(PHASES) and phase_at(float("nan"), *times) == "unknown"


def test_lock_comparison_from_the_saved_runs(job):
    """comparison.json's lost-lock comparison recomputed from both designs' saved runs."""
    config, out, summary = job
    s = json.loads((out / "comparison.json").read_text())
    lost = {}
    for d in DESIGNS:
        r = read_npz(out / "sweeps" / OBSERVER / d / "runs" / "result.npz")
        at = r["lost_lock"].reshape(-1).astype(bool)
        lost[d] = {(float(sp), float(ld), int(k)) for sp, ld, k in zip(
            r["grid/speed_pu"].reshape(-1)[at], r["grid/load_pu"].reshape(-1)[at],
            r["grid/case"].reshape(-1)[at])}
    c = s["observers"][OBSERVER]["lock_comparison"]
    assert (c["paper"], c["tuned"]) == (len(lost["paper"]), len(lost["tuned"]))
    assert c["fewer"] == (len(lost["tuned"]) < len(lost["paper"]))
    assert len(c["only_tuned"]) == len(lost["tuned"] - lost["paper"])
    assert len(c["only_paper"]) == len(lost["paper"] - lost["tuned"])
    assert "## Lost lock: tuned against paper" in (out / "comparison.md").read_text()
    # each lost run carries the analysis's status at its grid point, as saved
    # (the analysis grid is the runs' grid, point for point)
    for d in DESIGNS:
        r = read_npz(out / "sweeps" / OBSERVER / d / "runs" / "result.npz")
        a = read_npz(out / "sweeps" / OBSERVER / d / "analysis" / "result.npz")
        at = r["lost_lock"].reshape(-1).astype(bool)
        where = s["observers"][OBSERVER]["designs"][d]["lost_lock_where"]
        assert [w["analysis_status"] for w in where] == a["status"].reshape(-1)[at].tolist()
        # and when it lost lock, as saved, with the phase of the run then under way
        t_lost = r["t_lost"].reshape(-1)
        assert np.all(np.isnan(t_lost[~at])) and np.all((t_lost[at] >= 0)
                                                         & (t_lost[at] <= config.t_end))
        assert [w["t_lost_s"] for w in where] == t_lost[at].tolist()
        # tuning.scenarios.VAL_RAMP, VAL_LOAD_STEP on the sampling grid
        t0, t1, t_load = (round(f * config.t_end / config.T_s) * config.T_s
                          for f in (0.1, 0.3, 0.6))
        for w in where:
            t = w["t_lost_s"]
            want = ("start" if t < t0 else "ramp" if t < t1 else "steady" if t < t_load
                    else "loaded")
            assert w["phase"] == want
    # the tuning record says how many training runs the low-speed rule left out and how
    # many it kept without their load step (the ESO declares no limit: none)
    problem = config.tuning_problem(OBSERVER)
    t = s["observers"][OBSERVER]["tuning"]
    assert (t["train_runs"], t["train_runs_left_out"], t["train_runs_unloaded"]) == (
        problem.n_train, 0, 0)
    assert t["low_speed_limit_pu"] == problem.low_speed_limit_pu == 0.0


def _strip_timing(path):
    """A file of the job without the measurements of the machine (`TIMING_KEYS`)."""
    if path.suffix == ".json":
        s = json.loads(path.read_text())
        for e in s["observers"].values():
            for k in TIMING_KEYS:
                e.pop(k)
        return s
    # comparison.md: the last column of the table is the observer step time
    return re.sub(r"\| [^|]+ \|\n", "|\n", path.read_text())


def test_resume_gives_the_same_files(job, tmp_path, monkeypatch):
    config, out, _ = job
    part = tmp_path / "part"
    monkeypatch.setenv(STOP_ENV, "4")  # tuning, cost, two chunks of runs
    with pytest.raises(CompareInterrupted):
        run_comparison(config, part, progress=False, log=None, batch_size=2)
    assert not (part / "comparison.json").exists()
    assert (part / "tuned" / f"{OBSERVER}.json").is_file()
    monkeypatch.delenv(STOP_ENV)
    run_comparison(config, part, progress=False, log=None, batch_size=2)
    for f in ("comparison.json", "comparison.md"):
        assert _strip_timing(part / f) == _strip_timing(out / f), f
    for sub in ("runs", "analysis"):
        a = read_npz(out / "sweeps" / OBSERVER / "tuned" / sub / "result.npz")
        b = read_npz(part / "sweeps" / OBSERVER / "tuned" / sub / "result.npz")
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    # another configuration in the same folder is refused
    with pytest.raises(ValueError, match="another configuration"):
        run_comparison(tiny(noise_std=0.03), part, progress=False, log=None)


# two devices: the worker compiles every program anew for them (50 s); the sweep runner's
# sharding over devices is checked in the fast suite by tests/test_sweep.py, so here the
# fast case is one device (the worker's programs are the parent's: compilation-cache hits)
@pytest.mark.parametrize("n_devices", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_worker_processes_and_devices_give_the_same_files(job, tmp_path, monkeypatch,
                                                          n_devices):
    """`jobs` > 1: the observer's part runs in a worker process (`tuning.compare.worker`),
    here with one or two CPU devices over which its sweeps are sharded, and the parent
    assembles the same files as the one-process, one-device job. Equal to rounding, not
    bitwise: with `batch_size` the vmap width is the same, but XLA compiles the program
    sharded over two devices differently (the last digit of some metrics differs)."""
    config, out, _ = job
    par = tmp_path / "par"
    if n_devices > 1:
        monkeypatch.setenv("XLA_FLAGS",
                           f"--xla_force_host_platform_device_count={n_devices}")
    run_comparison(config, par, progress=False, log=None, jobs=2, batch_size=2)
    assert (par / "observers" / f"{OBSERVER}.json").is_file()
    assert (par / "logs" / f"{OBSERVER}.log").is_file()
    manifest = json.loads((par / "sweeps" / OBSERVER / "paper" / "runs" / "sweep.json"
                           ).read_text())
    assert manifest["devices"]["count"] == n_devices
    _assert_close(_strip_timing(par / "comparison.json"),
                  _strip_timing(out / "comparison.json"))
    for sub in ("runs", "analysis"):
        a = read_npz(out / "sweeps" / OBSERVER / "paper" / sub / "result.npz")
        b = read_npz(par / "sweeps" / OBSERVER / "paper" / sub / "result.npz")
        for k in a:
            if np.issubdtype(a[k].dtype, np.floating):
                np.testing.assert_allclose(a[k], b[k], rtol=1e-12, atol=1e-12, err_msg=k)
            else:
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert _strip_timing(par / "comparison.md") == _strip_timing(out / "comparison.md")
    with pytest.raises(ValueError, match="jobs"):
        run_comparison(config, par, progress=False, log=None, jobs=0)


def _assert_close(a, b, path=""):
    """Equal trees (dicts, lists, strings, ints, None), floats to 1e-12 relative."""
    if isinstance(a, dict):
        assert sorted(a) == sorted(b), path
        for k in a:
            _assert_close(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (u, v) in enumerate(zip(a, b)):
            _assert_close(u, v, f"{path}[{i}]")
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-12, abs=1e-12), path
    else:
        assert a == b, path


def test_config_errors():
    with pytest.raises(ValueError, match="observers"):
        CompareConfig(observers=("nope",))
    with pytest.raises(ValueError, match="speeds_pu"):
        CompareConfig(speeds_pu=(0.0, 0.5))
    with pytest.raises(ValueError, match="cases"):
        CompareConfig(cases=((1.0, 1.0, 1.0),))
    with pytest.raises(ValueError, match="tuner"):
        CompareConfig(tuner="sgd")
    for bad, match in ((((OBSERVER, (("w9", 1.0),)),), "no design coordinate"),
                       (((OBSERVER, (("w_tf", -1.0),)),), "finite value > 0"),
                       ((("eso", ()),), "not among the compared observers"),
                       (((OBSERVER, ()), (OBSERVER, ())), "given twice"),
                       ((("nope", ()),), "no registered observer")):
        with pytest.raises(ValueError, match=match):
            tiny(tuned_designs=bad)
    for bad in (0.0, -30.0, math.inf, "30", True):
        with pytest.raises(ValueError, match=r"speed_from_angle=.*frequency > 0 \(Hz\)"):
            CompareConfig(speed_from_angle=bad)


def test_speed_from_angle_runs_and_tunes_with_the_tracked_speed(job):
    """`speed_from_angle`: absent from the configuration's JSON (and fingerprint) unless
    given; the tuner's problem takes it; each run's metrics are those of a direct
    `simulate` whose controller takes the speed of `pmsmjax.SpeedFromAngle` (the runs
    differ from those on the observer's own speed: the job's runs of the paper design,
    which test_metrics_equal_direct_simulate checks against direct runs); the report's
    header says so."""
    from tuning.compare.points import run_point

    plain, out = job[0], job[1]
    tracked = tiny(speed_from_angle=30)
    assert plain == tiny()
    assert "speed_from_angle" not in plain.to_dict()
    assert tracked.to_dict()["speed_from_angle"] == 30.0
    assert plain.fingerprint() != tracked.fingerprint()
    assert tracked.tuning_problem(OBSERVER).speed_from_angle == 30.0
    assert plain.tuning_problem(OBSERVER).speed_from_angle is None
    assert CompareConfig.from_dict(tracked.to_dict()) == tracked
    grid = tracked.grid(index=True)
    pts = {k: jnp.asarray(v) for k, v in grid.items()}
    got = jax.jit(jax.vmap(lambda p: run_point(None, tracked, OBSERVER, p)))(pts)
    own = read_npz(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz")
    _, traj = _direct(tracked)
    want = jax.jit(lambda tr: run_metrics(tr, tracked))(traj)
    for k in ("static_deg", "rms_deg", "noise_rad_s"):
        np.testing.assert_allclose(got[k], want[k], rtol=1e-9, atol=1e-12, err_msg=k)
    assert np.max(np.abs(np.asarray(got["noise_rad_s"])
                         - np.asarray(own["noise_rad_s"]).reshape(-1))) > 1e-3
    md = markdown(dict(motor="zhang750", config=tracked.to_dict(), skipped={}, observers={},
                       grid=dict(n_runs=8, speeds_pu=[0.5], loads_pu=[0.0, 1.0],
                                 cases=[{}, {}])))
    assert "takes the speed of the observer's angle (30 Hz tracking loop)" in md


def test_a_design_tuned_elsewhere_runs_as_the_same_design_tuned_here(job, tmp_path):
    """`--tuned-from` / `tuned_designs`: the output folder of a tuning run (its
    design.json and summary.json, as `tuning.report.write_report` names them) gives the
    observer's "tuned" design; given the coordinates the job's own tuner found, the job
    runs nothing to tune and its tuned design's metrics equal the job's to round-off.
    A folder tuned on another drive, or without the files, is refused by name."""
    from tuning.report.summary import DESIGN_FILE, SUMMARY_FILE

    config, _, summary = job
    coords = summary["observers"][OBSERVER]["tuning"]["coordinates"]
    folder = tmp_path / "tuned"
    folder.mkdir()
    (folder / DESIGN_FILE).write_text(json.dumps({"observer": OBSERVER,
                                                  "coordinates": coords}))
    (folder / SUMMARY_FILE).write_text(json.dumps({"motor": "stumper_mt5"}))
    with pytest.raises(ValueError, match="tuned on 'stumper_mt5'; this comparison runs"):
        tuned_designs_from([str(folder)], config.motor)
    (folder / SUMMARY_FILE).write_text(json.dumps({"motor": config.motor}))
    with pytest.raises(ValueError, match="not the output folder of a `python -m tuning`"):
        tuned_designs_from([str(tmp_path)], config.motor)
    given = tuned_designs_from([str(folder)], config.motor)
    assert given == ((OBSERVER, tuple(sorted(coords.items()))),)
    cfg = tiny(tuner="none", analysis=False, tuned_designs=given)
    assert CompareConfig.from_dict(cfg.to_dict()) == cfg
    got = run_comparison(cfg, tmp_path / "job", progress=False, log=None, batch_size=2)
    e = got["observers"][OBSERVER]
    assert e["tuning"]["tuner"] == "given" and e["tuning"]["coordinates"] == coords
    want = summary["observers"][OBSERVER]["designs"]
    for d in DESIGNS:
        for k in ("lost_lock", "static_rms_deg", "static_worst_deg", "rms_worst_deg",
                  "noise_median_rad_s", "settle_worst_s"):
            np.testing.assert_allclose(e["designs"][d][k], want[d][k], rtol=1e-9,
                                       err_msg=f"{d} {k}")
    assert f"for {OBSERVER}, the design a full tuning run" in markdown(got)
    assert "small training problem" in markdown(summary)


def test_figures(job):
    from tuning.compare.plots import hardest_point, plot_comparison

    config, out, summary = job
    paths = plot_comparison(summary, out)
    assert sorted(p.name for p in paths) == ["metrics.png", "robustness_maps.png",
                                             "traces.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
    # the hardest scenario is the run with the largest RMS angle error (one observer)
    res = read_npz(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz")
    idx = hardest_point(summary, out)
    assert res["rms_deg"][idx] == np.max(res["rms_deg"])
    assert res["trace_theta_deg"].shape[-1] <= TRACE_SAMPLES + 1


def test_cli_dispatch(capsys):
    from tuning.__main__ import main

    # `python -m tuning compare ...` reaches the comparison's parser; a bad configuration
    # is a one-line error with status 2, before anything is computed
    assert main(["compare", "--observers", "nope", "--no-plot"]) == 2
    assert "CompareConfig(observers=...)" in capsys.readouterr().err
    # the shared sweep options (chunking, resume, several processes) are checked too
    assert main(["compare", "--num-processes", "2", "--no-plot"]) == 2
    assert "--coordinator" in capsys.readouterr().err
    assert main(["compare", "--tuned-from", "no-such-folder", "--no-plot"]) == 2
    assert "`--tuned-from no-such-folder`: not the output folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["compare", "--jobs", "0", "--no-plot"])
    assert e.value.code == 2 and "--jobs" in capsys.readouterr().err
    from tuning.compare.cli import jobs_for

    assert jobs_for("auto", distributed=True) == 1 and jobs_for(3, distributed=False) == 3
    assert 1 <= jobs_for("auto", distributed=False) <= 4
    with pytest.raises(SystemExit) as e:
        main(["compare", "--help"])
    assert e.value.code == 0
    assert "--chunk-size" in capsys.readouterr().out


def test_cli_starts_no_jax_backend_before_jax_distributed():
    """Under --coordinator, jax.distributed must start before JAX's backend: parsing
    the command line and checking the sweep options must not compute anything (a fresh
    process: this one has long started its backend)."""
    import subprocess
    import sys

    code = ("import pmsmjax as pj\n"
            "pj.runtime.configure()\n"
            "from jax._src import xla_bridge as xb\n"
            "from tuning.compare.cli import build_parser\n"
            "from pmsmjax.cli._sweep_options import sweep_settings\n"
            "a = build_parser().parse_args(['--coordinator', 'localhost:1', "
            "'--num-processes', '2', '--process-id', '0', '--quick'])\n"
            "sweep_settings(a, out=a.out)\n"
            "print('started' if xb.backends_are_initialized() else 'not started')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("not started")


def test_analysis_not_run_is_flagged(job):
    config, out, summary = job
    runs = read_npz(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz")
    m = aggregate(runs, None, config, config.grid())
    assert m["feasible_fraction"] is None and "feasible_fraction" in m["flags"]
    assert m["static_worst_deg"] == summary["observers"][OBSERVER]["designs"]["paper"][
        "static_worst_deg"]


def test_lost_runs_carry_the_analysis_status(job):
    """`aggregate` attaches to each lost run the analysis's verdict and status at its grid
    point (saved runs with two of them marked lost, the analysis at those points set to
    failed and to feasible)."""
    config, out, summary = job
    runs = dict(read_npz(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz"))
    feas = dict(read_npz(out / "sweeps" / OBSERVER / "paper" / "analysis" / "result.npz"))
    n = runs["lost_lock"].size
    lost = np.zeros(n, bool)
    lost[[1, n - 1]] = True
    runs["lost_lock"] = lost.reshape(runs["lost_lock"].shape)
    status = feas["status"].reshape(-1).copy()
    feasible = feas["feasible"].reshape(-1).copy()
    status[[1, n - 1]], feasible[[1, n - 1]] = (-1, 0), (False, True)
    feas["status"] = status.reshape(feas["status"].shape)
    feas["feasible"] = feasible.reshape(feas["feasible"].shape)
    m = aggregate(runs, feas, config, config.grid())
    assert [(w["analysis_status"], w["feasible"]) for w in m["lost_lock_where"]] == [
        (-1, False), (0, True)]
    assert m["analysis_failed"] == int(np.sum(status < 0))


def _equilibria_numpy(obs, plant, w, i_dq):
    """Every equilibrium of `obs`'s error dynamics at speed w, current i_dq, found without
    the analysis module: SciPy's root finder on error_rhs (scaled) from 24 starting
    angles, roots merged modulo 2 pi; stability from the eigenvalues of a
    central-difference Jacobian. Returns [(angle, stable)]."""
    import warnings

    import equinox as eqx
    import scipy.optimize

    from pmsmjax.observers import OperatingPoint

    op = OperatingPoint(jnp.asarray(w), jnp.asarray(i_dq))
    sc = np.asarray(obs.error_scale(op, plant))
    k = obs.coordinates.angle
    f_jit = eqx.filter_jit(lambda z, o: o.error_rhs(z * sc, op, plant) / sc)

    def f(z):
        return np.asarray(f_jit(jnp.asarray(z), obs))

    roots = []
    for a0 in np.linspace(-math.pi, math.pi, 24, endpoint=False):
        z0 = np.zeros(len(sc))
        z0[k] = a0 / sc[k]
        with warnings.catch_warnings():  # "not making progress" at an exact root too
            warnings.simplefilter("ignore", RuntimeWarning)
            z = scipy.optimize.fsolve(f, z0, xtol=1e-12)
        if np.max(np.abs(f(z))) > 1e-9:  # not a root: this start went astray
            continue
        z[k] = math.remainder(z[k] * sc[k], 2 * math.pi) / sc[k]
        if any(abs(math.remainder(z[k] * sc[k] - r[0], 2 * math.pi)) < 1e-6 for r in roots):
            continue
        h = 1e-6
        J = np.column_stack([(f(z + h * e) - f(z - h * e)) / (2 * h) for e in np.eye(len(z))])
        roots.append((z[k] * sc[k], bool(np.max(np.linalg.eigvals(J).real) < 0)))
    return roots


def test_feasibility_against_an_independent_root_search(job):
    """The analysis metric (`feasible_fraction`) recomputed without the analysis module:
    at every point of the grid, the equilibria of the paper design's error dynamics by
    SciPy's root finder from many starting angles; feasible where the principal one (the
    smallest angle error) is stable and no other is."""
    config, out, summary = job
    drive = config.drive()
    plant = drive.three_phase_motor
    grid = config.grid()
    cases = np.asarray(config.cases)[grid["case"]]
    want = []
    for speed, load, k in zip(grid["speed_pu"], grid["load_pu"], cases):
        obs = pj.observers.make_observer(OBSERVER, drive,
                                         motor=observer_model(drive, *map(float, k)))
        # the run's load brakes (its torque opposes the rotation): i_q takes the speed's sign
        i_q = np.sign(speed) * load * drive.tau_rated / (drive.k_tau * plant.psi_f)
        roots = _equilibria_numpy(obs, plant, speed * drive.w_rated, [0.0, i_q])
        assert roots, (speed, load, k)
        principal = min(roots, key=lambda r: abs(r[0]))
        want.append(principal[1] and sum(r[1] for r in roots) == 1)
    feas = read_npz(out / "sweeps" / OBSERVER / "paper" / "analysis" / "result.npz")
    np.testing.assert_array_equal(np.asarray(feas["feasible"]).reshape(-1), want)
    got = summary["observers"][OBSERVER]["designs"]["paper"]
    assert got["feasible_fraction"] == pytest.approx(np.mean(want), abs=1e-12)
    assert got["analysis_failed"] == 0
