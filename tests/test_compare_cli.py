"""`python -m tuning compare` from its command line, in a separate process: the quickest
job it has (`--quick`, one observer, one worker process, no figures).

What is checked, and against what:

- exit status 0, and the files it documents (comparison.json, comparison.md,
  timing.json, the per-run sweep results) in `--out`;
- the configuration in comparison.json is the one `--quick` documents (4 kHz, 0.3 s,
  speeds +-{0.05, 0.25, 1} p.u., loads {0, 1}, five mismatch cases, paper designs only,
  no analysis), and the grid holds their product: 6 x 2 x 5 = 60 runs of
  0.3 s / 250 us = 1200 steps;
- the per-observer numbers of comparison.json recomputed in NumPy from the per-run
  results the job saved (result.npz): worst and RMS static error over the runs that kept
  lock, worst run RMS, the lost-lock count and where, settling and noise statistics. This
  is a second route (the definitions of `tuning.compare`'s module docstring applied
  here, not the job's `aggregate`);
- the saved decimated angle-error traces are samples of the same runs: their largest
  magnitude never exceeds the run's `max_abs_deg`, and each starts at zero (the observer
  starts on the true state);
- the table printed on stdout is the one in comparison.md;
- a bad option ends with exit status 2 and a message naming the option.

The first run on a machine compiles (about 30 s on two cores); with the persistent
compilation cache of `pmsmjax.runtime` it takes about 13 s.
"""

import json
import math
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest


ROOT = pathlib.Path(__file__).resolve().parents[1]
OBSERVER = "parallel-model"


def _run(*args, timeout=300):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get(
        "PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.run([sys.executable, "-m", "tuning", "compare", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare_cli") / "job"
    p = _run("--quick", "--observers", OBSERVER, "--jobs", "1", "--no-plot",
             "--no-progress", "--out", str(out))
    assert p.returncode == 0, p.stderr[-3000:]
    return out, p.stdout


def test_files_and_configuration(job):
    out, _ = job
    for f in ("comparison.json", "comparison.md", "timing.json"):
        assert (out / f).is_file(), f
    assert (out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz").is_file()
    assert not list(out.glob("*.png"))  # --no-plot
    s = json.loads((out / "comparison.json").read_text())  # strict JSON
    c = s["config"]
    assert c["observers"] == [OBSERVER] and c["motor"] == "zhang750"
    assert c["T_s"] == 250e-6 and c["t_end"] == 0.3
    assert c["speeds_pu"] == [0.05, 0.25, 1.0] and c["loads_pu"] == [0.0, 1.0]
    assert len(c["cases"]) == 5 and c["cases"][0] == [1.0, 1.0, 1.0, 1.0]
    assert c["tuner"] == "none" and c["analysis"] is False
    assert sorted(s["grid"]["speeds_pu"]) == [-1.0, -0.25, -0.05, 0.05, 0.25, 1.0]
    assert s["grid"]["n_runs"] == 6 * 2 * 5
    timing = json.loads((out / "timing.json").read_text())
    assert timing["runs_per_design"] == 60
    assert timing["steps_per_run"] == round(0.3 / 250e-6) == 1200
    # the tuned design is flagged, not invented
    tuned = s["observers"][OBSERVER]["designs"]["tuned"]
    assert "all" in tuned["flags"]


def test_summary_numbers_from_the_saved_runs(job):
    out, _ = job
    s = json.loads((out / "comparison.json").read_text())
    m = s["observers"][OBSERVER]["designs"]["paper"]
    with np.load(out / "sweeps" / OBSERVER / "paper" / "runs" / "result.npz") as f:
        r = {k: f[k] for k in f.files}
    lost = r["lost_lock"].reshape(-1).astype(bool)
    keep = ~lost
    assert m["n_runs"] == lost.size == 60
    assert m["lost_lock"] == int(lost.sum())
    static = r["static_deg"].reshape(-1)[keep]
    assert keep.any()
    assert m["static_worst_deg"] == pytest.approx(np.abs(static).max(), rel=1e-12)
    assert m["static_rms_deg"] == pytest.approx(math.sqrt(np.mean(static ** 2)), rel=1e-12)
    assert m["rms_worst_deg"] == pytest.approx(r["rms_deg"].reshape(-1)[keep].max(),
                                               rel=1e-12)
    settle = r["settle_s"].reshape(-1)[keep]
    assert m["n_unsettled"] == int(np.sum(np.isnan(settle)))
    settled = settle[np.isfinite(settle)]
    if settled.size:
        assert m["settle_worst_s"] == pytest.approx(settled.max(), rel=1e-12)
        assert m["settle_median_s"] == pytest.approx(np.median(settled), rel=1e-12)
    noise = r["noise_rad_s"].reshape(-1)[keep]
    assert m["noise_median_rad_s"] == pytest.approx(np.median(noise), rel=1e-12)
    assert m["noise_worst_rad_s"] == pytest.approx(noise.max(), rel=1e-12)
    # where lock was lost: the grid coordinates of those runs
    cases = s["config"]["cases"]
    want = sorted((float(sp), float(ld), *map(float, cases[int(c)])) for sp, ld, c in zip(
        r["grid/speed_pu"].reshape(-1)[lost], r["grid/load_pu"].reshape(-1)[lost],
        r["grid/case"].reshape(-1)[lost]))
    got = sorted((w["speed_pu"], w["load_pu"], w["k_d"], w["k_q"], w["k_R"], w["k_psi"])
                 for w in m["lost_lock_where"])
    assert got == want
    # the traces are samples of the runs: bounded by the run's largest error, zero at t = 0
    tr = r["trace_theta_deg"].reshape(60, -1)
    assert np.all(np.abs(tr).max(-1) <= r["max_abs_deg"].reshape(-1) * (1 + 1e-12))
    np.testing.assert_allclose(tr[:, 0], 0.0, atol=1e-9)
    assert np.all(r["rms_deg"] <= r["max_abs_deg"] * (1 + 1e-12))


def test_printed_table_is_the_markdown_table(job):
    out, stdout = job
    md = (out / "comparison.md").read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith(f"| {OBSERVER} |")]
    assert len(rows) == 2  # paper and tuned
    # the last column is a timing measurement; the rest is the job's numbers
    for row in rows:
        assert row in stdout
    s = json.loads((out / "comparison.json").read_text())
    m = s["observers"][OBSERVER]["designs"]["paper"]
    assert f"| {m['static_worst_deg']:.2f} | {m['static_rms_deg']:.2f} |" in rows[0]
    assert stdout.rstrip().splitlines()[-1].startswith("wall time")


@pytest.mark.parametrize("args, named", [
    (["--tuner", "sgd"], "--tuner"),
    (["--observers", "no-such-observer"], "observers"),
    (["--tune-steps", "many"], "--tune-steps"),
])
def test_bad_argument_exits_2_naming_it(args, named, tmp_path):
    p = _run(*args, "--no-plot", "--out", str(tmp_path / "bad"), timeout=120)
    assert p.returncode == 2
    assert named in p.stderr and "error" in p.stderr
    assert not (tmp_path / "bad" / "comparison.json").exists()
