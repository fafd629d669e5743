"""The main job: `make run` = `python -m tuning --out results` (gain tuning under inductance
mismatch), here in its `--quick` mode, as a user runs it (a subprocess).

The `pmsmjax simulate` default run that used to be the main job is tested in
`test_cli.py::test_simulate_default_run`.
"""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

import tuning as tg


ROOT = pathlib.Path(__file__).parents[1]


def test_makefile_runs_the_tuner():
    make = (ROOT / "Makefile").read_text()
    run = make[make.index("\nrun:"):].split("\n\n")[0]
    assert "-m tuning --out $(OUT)" in run


@pytest.mark.timeout(1200)
def test_main_job_quick(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, "-m", "tuning", "--quick", "--no-progress", "--out", str(out)],
        capture_output=True, text=True, timeout=1200, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    assert "after JAX started its backend" not in proc.stderr  # configured in time
    printed = proc.stdout
    assert str(out / "summary.json") in printed

    for name in ("summary.json", "tuned_schedule.eqx", "loss_curve.png", "heatmaps.png",
                 "time_trace.png", "per_scenario.png"):
        assert (out / name).stat().st_size > 0, name
    s = json.loads((out / "summary.json").read_text())
    assert set(tg.REQUIRED_KEYS) <= set(s)
    cfg = tg.TuningConfig.quick()
    assert s["config"]["n_mismatch"] == cfg.n_mismatch and s["motor"] == "zhang750"
    assert s["observer"] == "eso" and s["observer_class"] == "ESOObserver"
    assert s["parametrisation"] == "scheduled" and s["baseline_label"] == "(38)/(25)"
    assert s["tuned_parameters"] == list(tg.TUNABLE)
    # the tuned design beats the paper's (38)/(25) on the robust loss, on the training
    # grid and on the held-out mismatch, and is feasible on every scenario; the default
    # objective leaves no training scenario worse than its tolerance
    assert s["objective"] == "no_regression"
    assert s["accounting"]["train"]["worse"] == 0
    assert s["accounting"]["train"]["tolerance_pct"] == pytest.approx(
        100 * cfg.regression_tol)
    assert s["tuned_loss"] < s["baseline_loss"]
    assert s["heldout_tuned_loss"] < s["heldout_baseline_loss"]
    assert s["improvement_pct"]["heldout"] > 0
    assert s["feasible"] is True
    # the verdict: "beats" only if the objective is lower on the training, held-out and
    # validation scenarios and no scenario of any of them got worse; otherwise where not
    acc, v = s["accounting"], s["verdict"]
    holds = all(s["beats_baseline"][k] and acc[k]["worse"] == 0
                for k in ("train", "heldout", "validation"))
    assert v["holds"] is holds
    if holds:
        assert "tuned beats (38)/(25)" in printed and not v["where_not"]
    else:
        assert "tuned does NOT beat (38)/(25) everywhere" in printed
        assert v["where_not"] and all(line in printed for line in v["where_not"])
    assert f"validation: {acc['validation']['improved']} of {acc['validation']['n']}" \
        in printed
    assert s["validation_baseline_loss"] > 0 and s["validation_tuned_loss"] > 0
    assert len(s["scenarios"]["validation"]) == acc["validation"]["n"] == 2 * len(
        cfg.val_speeds_pu) * len(cfg.val_cases)
    assert all(s["feasible_per_scenario"]["train"]) and all(s["feasible_per_scenario"]["heldout"])
    n_train = cfg.n_mismatch ** 2 * len(cfg.speeds_pu) * len(cfg.loads_pu)
    assert len(s["scenarios"]["train"]) == n_train
    row = s["scenarios"]["heldout"][0]
    assert {"k_d", "k_q", "speed_pu", "load_pu", "paper", "tuned"} <= set(row)
    assert {"loss", "pos_rms_deg", "settle_ms", "noise_rad_s", "feasible"} <= set(row["tuned"])
    assert len(s["loss_history"]) == s["histories"]["tuned"]["n_simulations"][-1] // n_train
    assert np.all(np.isfinite(s["loss_history"]))
    assert s["wall_time_s"] > 0
    nodes = s["tuned_design"]["nodes"]
    assert nodes["s_pu"] == list(cfg.nodes_pu)
    assert all(v > 0 for q in ("zeta1", "ratio", "zeta2", "w2") for v in nodes[q])
    # the gradient-free baseline had the same number of simulations
    h = s["histories"]
    assert h["random_search"]["n_simulations"][-1] == h["tuned"]["n_simulations"][-1]
    # the gains table for firmware carries the sampling period, the objective and the
    # verdict of this run; a verdict that does not hold is announced on stderr and in
    # gains.h (a compiler warning)
    g = json.loads((out / "gains.json").read_text())
    assert g["T_s"] == s["config"]["T_s"] and g["objective"] == s["objective"]
    assert g["verdict"] == {"holds": v["holds"], "baseline": s["baseline_label"],
                            "where_not": v["where_not"]}
    header = (out / "gains.h").read_text()
    assert f"#define PMSMJAX_GAINS_VERDICT_HOLDS {int(holds)}" in header
    assert ("did NOT pass the tuner's checks" in proc.stderr) is (not holds)
    assert ("#warning" in header) is (not holds)
    # the saved schedule reloads
    back = tg.load_schedule(out)
    assert np.allclose(tg.schedule_table(back)["w2"], nodes["w2"], rtol=0, atol=0)
    print(f"main job (--quick): wall {s['wall_time_s']:.1f} s, tuned {s['tuned_loss']:.3f} "
          f"vs (38) {s['baseline_loss']:.3f}")
