"""What a firmware engineer looks at before flashing gains: `pmsmjax gains` (the table's
verdict, the gains versus speed next to the paper's, the discrete observer's poles
versus speed) and the Bode plot of `pmsmjax response --plot`; the poles themselves
(`analysis.discrete_poles`) against the continuous linearisation."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from pmsmjax import analysis
from pmsmjax.cli.__main__ import main
from pmsmjax.cli._response import PLOT_ORDERS
from pmsmjax.observers import make_observer

from .helpers import scheduled_gains_table


@pytest.mark.parametrize("name,motor", [("eso", "zhang750"), ("parallel-model",
                                                               "stumper_mt5")])
def test_discrete_poles_approach_the_continuous_ones(name, motor):
    """z = exp(T_s lambda) + O(T_s^2): ten times smaller T_s, about a hundred times
    closer (lambda: eigenvalues of the continuous linearisation)."""
    drive = pj.preset(motor)
    obs, plant = make_observer(name, drive), drive.three_phase_motor
    w, i = 0.5 * float(drive.w_rated), jnp.asarray([0.0, 0.3 * float(drive.base.I_b)])
    lam = np.linalg.eigvals(np.asarray(analysis.linearization(obs, plant, w, i)))
    dist = []
    for T_s in (1e-4, 1e-5):
        z = np.asarray(analysis.discrete_poles(obs, plant, w, i, T_s))
        assert z.shape == lam.shape and np.all(np.abs(z) < 1)
        dist.append(max(np.min(np.abs(zz - np.exp(T_s * lam))) for zz in z))
    assert 70 < dist[0] / dist[1] < 130, dist  # measured 95 and 94


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """A tuned-looking ESO schedule's gains table whose verdict does not hold."""
    cfg = tg.TuningProblem.quick()
    t, _ = scheduled_gains_table(cfg.drive(), cfg.T_s, verdict={
        "holds": False, "baseline": "zhang2022 (38)/(25)", "where_not": ["validation: worse"]})
    folder = tmp_path_factory.mktemp("tuned")
    pj.write_gains_table(t, folder)
    return cfg, t, folder


def test_gains_command_compares_tuned_and_paper(table, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    cfg, t, folder = table
    out = tmp_path / "check"
    assert main(["gains", "--design", str(folder), "--i-q", "0.3", "--plot", "--out",
                 str(out)]) == 0
    cap = capsys.readouterr()
    assert "did NOT beat" in cap.err and f"T_s = {cfg.T_s:g} s" in cap.out
    r = json.loads((out / "gains_check.json").read_text())
    assert (out / "gains.png").stat().st_size > 0 and (out / "poles.png").stat().st_size > 0
    assert r["T_s"] == cfg.T_s and r["verdict"]["holds"] is False
    # the tuned gains at the table's rows are the table's own gain columns (written by
    # the tuner from its schedule; here recomputed from the interpolated table)
    cols = pj._data._gains_table.table_columns(t)
    rows = np.searchsorted(cols["w_m"], np.asarray(r["w_m"]))
    for k in ("G1_11", "G1_21", "g2_2", "g3_2", "k_p"):
        np.testing.assert_allclose(r["gains"][k]["tuned"], cols[k][rows], rtol=1e-9,
                                   atol=1e-9 * np.max(np.abs(cols[k])))
    # the paper's gains: the paper design's own schedule; the poles at one speed, from
    # the Jacobian of one observer step directly (one compiled program for both, instead
    # of a hundred single operations)
    drive = cfg.drive()
    paper = make_observer("eso", drive)
    w = float(r["w_m"][5])
    tuned = pj.apply_gains_table(t, paper)
    i_a = jnp.asarray([0.0, 0.3 * float(drive.base.I_b)])

    @eqx.filter_jit
    def gain_and_step_jacobian(paper, tuned, w):
        g = paper.linear_gains(w, jnp.zeros(2))
        fn = analysis.discrete_error_map(tuned, drive.three_phase_motor, w, i_a, cfg.T_s)
        return g.G1[0, 0], jax.jacfwd(fn)(jnp.zeros(tuned.coordinates.n))

    G1_11, jac = gain_and_step_jacobian(paper, tuned, jnp.asarray(w))
    assert r["gains"]["G1_11"]["paper"][5] == pytest.approx(float(G1_11), rel=1e-12)
    z = np.linalg.eigvals(np.asarray(jac))
    assert r["max_abs_pole_tuned"][5] == pytest.approx(np.max(np.abs(z)), rel=1e-9)
    assert max(r["max_abs_pole_tuned"]) < 1 and max(r["max_abs_pole_paper"]) < 1


def test_response_plot(tmp_path, capsys, monkeypatch):
    """`response --plot` writes the Bode plot of a back-EMF observer (and the ripple
    curve of any observer); it needs --out."""
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # the orders of the plot's ripple curve (-25..25): the table's ripple is then the same
    # compiled program as the curve's (one harmonic balance compiled instead of two)
    orders = [str(h) for h in PLOT_ORDERS]
    assert main(["response", "--motor", "li_dtp", "--observer", "fa-leso", "--speed", "0.5",
                 "--orders", *orders, "--plot", "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "response.png").stat().st_size > 0
    from pmsmjax.cli import ObserverChoice
    from pmsmjax.cli._response import response_curves

    drive = pj.preset("li_dtp")
    obs = make_observer("fa-leso", drive)
    choice = ObserverChoice("fa-leso", obs, drive.three_phase_motor, {}, None)
    c = response_curves(choice, drive, 0.5, (0.0, 0.0), [1, -5, 7], 1e-4)
    # the ripple curve holds the orders the table prints (all of them)
    rep = json.loads((tmp_path / "r" / "response.json").read_text())
    assert [it["order"] for it in rep["orders"]] == list(PLOT_ORDERS)
    for it in rep["orders"]:
        k = c["orders"].index(it["order"])
        assert c["ripple_deg"][k] == pytest.approx(it["angle_ripple_deg_per_pct"],
                                                   rel=1e-9, abs=1e-12)
    # discrete and continuous Bode data agree far below the Nyquist frequency
    b = c["bode"]
    low = np.abs(b["f_hz"]) < 50
    np.testing.assert_allclose(b["mag_db_discrete"][low], b["mag_db"][low], atol=0.05)
    capsys.readouterr()
    assert main(["response", "--plot"]) == 2
    assert "--out" in capsys.readouterr().err


def test_gains_command_on_a_constant_design(tmp_path, capsys):
    """A constant design (stumper's parallel-model estimator, every parameter 1.2 x the
    paper's): its parameters against the paper's, and its poles, over both signs of
    speed."""
    drive = pj.preset("stumper_mt5")
    paper = make_observer("parallel-model", drive)
    values = {k: 1.2 * float(v) for k, v in paper.design_parameters().items()}
    t = pj.gains_table_constant("parallel-model", values, dict(type(paper).design_units),
                                drive=drive.name, T_s=62.5e-6, objective="robust",
                                verdict={"holds": True, "baseline": "paper"})
    pj.write_gains_table(t, tmp_path / "tab")
    assert main(["gains", "--motor", "stumper_mt5", "--design", str(tmp_path / "tab"),
                 "--i-q", "0.3", "--out", str(tmp_path / "chk")]) == 0
    assert "warning" not in capsys.readouterr().err  # the verdict holds
    r = json.loads((tmp_path / "chk" / "gains_check.json").read_text())
    for k, g in r["gains"].items():
        np.testing.assert_allclose(g["tuned"], 1.2 * np.asarray(g["paper"]), rtol=1e-12)
    s = np.asarray(r["speed_pu"])
    assert s.min() < 0 < s.max() and r["T_s"] == 62.5e-6
    assert max(r["max_abs_pole_tuned"]) < 1 and max(r["max_abs_pole_paper"]) < 1
