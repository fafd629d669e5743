"""Runs both designs lose lock in (`tuning.judged`: ties of the accounting) and what the
analysis says at their end (`tuning.end_analysis`), on morawiec2023's
rotor-flux observer, whose paper design loses 12 of its 88 validation runs.

The analysis at each run's end is checked against `pmsmjax.analysis.equilibria` called
on its own (the public route, not the traced one the tuner vmaps), with the designed
equilibrium's rule written out here; and against the closed loop: a run whose end has no
equilibrium at all is lost in simulation, one whose end is feasible with a matched model
is held."""

import jax.numpy as jnp
import numpy as np

import tuning as tg
from pmsmjax import analysis
from tuning.pipeline import _lost_by_both
from tuning.scenarios import observer_model, operating_current


P = tg.TuningProblem(observer="rotor-flux")


def _run(table, **want):
    """Index of the first validation run whose row matches `want` (to 3 digits)."""
    return next(j for j, r in enumerate(table)
                if all(round(r[k], 3) == v for k, v in want.items()))


def _by_hand(space, drive, row):
    """The designed equilibrium's rule on `pmsmjax.analysis.equilibria` at the run's end:
    the paper's design with the run's observer model."""
    obs = space.observer(None, observer_model(drive, row["k_d"], row["k_q"], row["k_R"],
                                              row["k_psi"]))
    s1 = row["s1"]
    i_dq = operating_current(drive, jnp.asarray(row["load_pu"] * np.sign(s1)))
    eq = analysis.equilibria(obs, drive.three_phase_motor, s1 * float(drive.w_rated),
                             i_dq, max_roots=8)
    status = int(eq.status)
    if status < 0:
        return "failed"
    if status == 2:
        return "no equilibrium"
    valid = np.asarray(eq.valid)
    stable = np.asarray(eq.stable) & valid
    k = int(eq.principal)
    others = np.delete(stable, k)
    return "feasible" if stable[k] and not others.any() else "infeasible"


def test_the_end_of_a_run_lost_by_both_designs():
    """Three runs lost by both designs: the report's record of them
    (`tuning.pipeline._lost_by_both`, on hand-built lock flags) and the analysis at their
    ends that it carries, which is `tuning.end_analysis` of those runs (one vmapped
    program, traced and compiled once here: the record's rows are checked, not a second
    call of their own)."""
    space = tg.DesignSpace(P)
    drive = P.drive()
    vset = tg.validation_set(P)
    table = vset.table()
    runs = [_run(table, s1=0.4, k_d=1.0, k_q=1.0, k_R=1.0, k_psi=1.0),   # matched
            _run(table, s1=0.4, k_d=0.7, k_q=1.3),                        # L_d low, L_q high
            _run(table, s1=0.1, k_d=1.0, k_q=1.0, k_R=1.0, k_psi=1.1)]    # psi_f 10 % high
    assert runs == sorted(runs)  # the record's order (by run) is this one

    # the report's record: hand-built lock flags, the same three runs lost by both designs
    # and a fourth lost only by the tuned design (judged: not a tie, not in the record)
    n = vset.n
    lost = np.zeros(n, bool)
    lost[runs] = True
    lost_t = lost.copy()
    lost_t[_run(table, s1=0.8, k_d=1.0, k_q=1.0, k_R=1.0, k_psi=1.0)] = True
    z = jnp.zeros(n)

    # hand-built times of the losses: the feasible (matched) run lost after its load step
    t0, t1, t_load = (np.asarray(a) for a in (vset.t0, vset.t1, vset.t_load))
    t_lost = np.full(n, np.nan)
    t_lost[runs] = [t_load[runs[0]] + 1e-3, 0.5 * (t0[runs[1]] + t1[runs[1]]), 0.0]

    def metrics(flags):
        return tg.Metrics(rms_deg=z + 1, peak_deg=z, static_deg=z, noise_rad_s=z,
                          out_of_lock=z, lost_lock=jnp.asarray(flags), ok=z == 0, loss=z + 1,
                          t_lost=jnp.asarray(t_lost))

    verdict, said = {"holds": False, "where_not": []}, []
    _lost_by_both(P, space, vset, {"paper": metrics(lost), "tuned": metrics(lost_t)},
                  "tuned", None, np.zeros(n, bool), verdict, said.append)
    rows = verdict["lost_by_both"]
    # the analysis at each run's end: `tuning.end_analysis`'s rows, against the public
    # route by hand
    assert [r["run"] for r in rows] == runs
    for r in rows:
        assert set(r) >= {"run", "speed_pu", "load_pu", "analysis_status", "end"}
        assert (r["speed_pu"], r["load_pu"]) == (table[r["run"]]["s1"],
                                                 table[r["run"]]["load_pu"])
        assert r["end"] == _by_hand(space, drive, table[r["run"]]), r
        assert r["end"] in tg.END_VERDICTS
    assert [r["end"] for r in rows] == ["feasible", "no equilibrium", "no equilibrium"]
    # the closed loop agrees: the two ends with no equilibrium are lost, the matched one held
    ref = tg.Evaluator(P, space, vset.take(np.asarray(runs))).reference
    assert np.asarray(ref.lost_lock).tolist() == [False, True, True]
    # and says when: the two lost runs inside the run, the held one never
    t_end_lost = np.asarray(ref.t_lost)
    assert np.isnan(t_end_lost[0]) and np.all((t_end_lost[1:] >= 0)
                                              & (t_end_lost[1:] <= vset.t_end))

    assert {r["run"]: (r["t_lost_s"], r["phase"]) for r in rows} == {
        runs[0]: (t_lost[runs[0]], "loaded"), runs[1]: (t_lost[runs[1]], "ramp"),
        runs[2]: (0.0, "start")}
    line = verdict["where_not"][0]
    assert line.startswith("3 runs lost by both designs are ties")
    assert (f"2 {tg.END_VERDICTS['no equilibrium']}" in line
            and f"1 {tg.END_VERDICTS['feasible']}" in line)
    assert line.endswith("; those lost on the way, by phase: loaded 1")
    assert said[-1] == line
    # runs the low-speed rule sets apart are not in the record (nor analysed)
    verdict = {"holds": True, "where_not": []}
    _lost_by_both(P, space, vset, {"paper": metrics(lost), "tuned": metrics(lost_t)},
                  "tuned", None, lost, verdict, None)
    assert verdict["lost_by_both"] == [] and verdict["where_not"] == []
