"""`python -m tuning --observer parallel-model --motor stumper_mt5`: the estimator's
tunable design (tracking- and derivative-filter parameters) and the per-motor default
grid."""

import pytest

from tuning.__main__ import build_parser, config_from_args
from tuning.scenarios import MOTOR_DEFAULTS


def _config(*argv):
    return config_from_args(build_parser().parse_args(list(argv)))


def test_stumper_defaults_and_tunable_design():
    c = _config("--observer", "parallel-model", "--motor", "stumper_mt5")
    for k, v in MOTOR_DEFAULTS["stumper_mt5"].items():
        assert getattr(c, k) == (tuple(v) if isinstance(v, tuple) else v)
    assert c.design_kind == "constant" and set(c.quantities()) == {"v1", "v2", "T_LP"}
    paper = c.paper_design()
    assert paper is not None
    # an option given on the command line wins over the motor's default
    c2 = _config("--observer", "parallel-model", "--motor", "stumper_mt5", "--speeds",
                 "0.3")
    assert c2.speeds_pu == (0.3,) and c2.T_s == MOTOR_DEFAULTS["stumper_mt5"]["T_s"]
    # other motors keep the library defaults
    c3 = _config("--observer", "parallel-model", "--motor", "zhang750")
    assert c3.T_s == 125e-6


@pytest.mark.slow  # about 8 min on two shared cores (the gradient compiles for minutes)
def test_quick_tuning_runs(tmp_path):
    from tuning.__main__ import main

    assert main(["--observer", "parallel-model", "--motor", "stumper_mt5", "--quick",
                 "--out", str(tmp_path), "--no-progress", "--no-plot",
                 "--no-ablation"]) == 0
    assert (tmp_path / "summary.json").exists()
