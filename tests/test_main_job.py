"""The main job (`make run` = `pmsmjax simulate --out results`) on its built-in default."""

import json

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.__main__ import main


def test_main_job_default(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["simulate", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "status: successful" in printed

    for name in ("trajectory.npz", "recording.npz", "summary.json", "simulation.png"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    # The built-in default: zhang750, sensored FOC, 1.5 s at T_s = 125 us.
    assert summary["motor"] == "zhang750"
    assert summary["observer"] == "sensored"
    assert summary["T_s"] == 125e-6
    assert summary["steps"] == 12000
    assert summary["scenario"]["name"] == "default"
    assert summary["scenario"]["speed_pu"] == 0.5 and summary["scenario"]["load_pu"] == 0.5
    assert summary["controller"]["current_bandwidth_rad_s"] == pytest.approx(2 * np.pi * 500)
    assert summary["controller"]["speed_bandwidth_rad_s"] == pytest.approx(2 * np.pi * 5)
    assert summary["status"] == "successful"
    # The speed loop ends at its set-point, the settled error is small and the current
    # stays within the drive's limit.
    assert summary["final_speed"]["pu"] == pytest.approx(0.5, abs=5e-3)
    se = summary["speed_error_after_settling"]
    assert se["samples"] > 1000
    assert se["max_abs_pu"] < 0.02
    assert 0 < summary["max_current"]["A"] < pj.preset("zhang750").i_max
    print(f"main job: compile {summary['compile_time_s']:.2f} s, run "
          f"{summary['run_time_s']:.3f} s, wall {summary['wall_time_s']:.2f} s")

    rec = pj.load_recording(out / "recording.npz")
    assert rec.n == 12000
    assert np.max(rec.tau_L) == pytest.approx(0.5 * pj.preset("zhang750").tau_rated)
