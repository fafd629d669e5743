"""Output of a tuning run: `summary.json`, the tuned design (equinox serialisation) and
plots (loss curves, error-versus-mismatch heat maps before/after, a time trace), for any
tuned observer and parametrisation."""

from __future__ import annotations

import json
import math
import pathlib

import equinox as eqx
import numpy as np

import pmsmjax as pj

from ._export import gains_table
from ._parametrise import AbstractDesign, GainSchedule
from ._pipeline import TuningReport, descriptions, targets_reached
from .objectives import relative_change, report_objective
from .scenarios import TuningConfig


SCHEDULE_FILE = "tuned_schedule.eqx"
#: The drive the design was tuned for (after `set_params`), as a motor file.
MOTOR_FILE = "motor.toml"
SUMMARY_FILE = "summary.json"
PLOTS = ("loss_curve.png", "heatmaps.png", "time_trace.png", "per_scenario.png")
#: Relative change of a scenario's loss that counts as improved / worse when the
#: configuration gives none (the accounting uses `TuningConfig.regression_tol`, 1 % by
#: default, the tolerance of the "no_regression" objective).
CHANGE_TOL = 0.01

#: Keys every summary.json has (tests check them).
REQUIRED_KEYS = ("baseline_loss", "tuned_loss", "heldout_baseline_loss",
                 "heldout_tuned_loss", "feasible", "loss_history", "wall_time_s",
                 "scenarios", "tuned_design")


def _clean(x):
    """JSON-safe: numpy -> Python, NaN/inf -> None."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, np.generic):
        return _clean(x.item())
    if hasattr(x, "shape") and hasattr(x, "dtype"):  # jax array
        return _clean(np.asarray(x))
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _scenario_rows(report: TuningReport, split: str) -> list:
    scen = report.train if split == "train" else report.heldout
    rows = []
    for j, row in enumerate(scen.table()):
        for name in report.designs:
            m = report.metrics[name][split]
            f = report.feasibility[name][split]
            row[name] = dict(
                loss=float(m.loss[j]), pos_rms_deg=float(m.pos_rms_deg[j]),
                theta_ss_deg=float(m.theta_ss_deg[j]),
                settle_ms=1e3 * float(m.settle_s[j]), noise_rad_s=float(m.noise_rad_s[j]),
                w_bias_rad_s=float(m.w_bias_rad_s[j]),
                stab_penalty=float(m.stab_penalty[j]), ok=bool(m.ok[j]),
                feasible=bool(f["feasible"][j]), analysis_status=int(f["status"][j]),
                principal_stable=bool(f["principal_stable"][j]),
                n_nonzero_equilibria=int(f["n_nonzero"][j]),
                static_error_theory_deg=float(f["principal_theta_deg"][j]),
                stable_other_theta_deg=float(f["stable_other_theta_deg"][j]),
                max_real_eig=float(f["max_real_eig"][j]))
        rows.append(row)
    return rows


#: The scenario splits of a report, in the order they are reported.
SPLITS = ("train", "heldout", "validation")


def _split_set(report: TuningReport, split: str):
    return {"train": report.train, "heldout": report.heldout,
            "validation": report.validation}[split]


def accounting(report: TuningReport, split: str, tol: float | None = None) -> dict:
    """Per-scenario comparison of the tuned design with the baseline on `split`
    ("train", "heldout" or "validation"): how many scenarios improved or got worse
    (relative change of the scenario loss beyond `tol`), the worst regression and where,
    and the change of loss, RMS and static angle error per scenario (for the validation
    runs the static error is the mean over the last part of the run, see
    `tuning.validation`). `tol` defaults to the configuration's `regression_tol`."""
    tol = getattr(report.config, "regression_tol", CHANGE_TOL) if tol is None else tol
    scen = _split_set(report, split)
    b, t = report.metrics["paper"][split], report.metrics["tuned"][split]
    lb, lt = np.asarray(b.loss, float), np.asarray(t.loss, float)
    rel = relative_change(lt, lb)
    rows = scen.table()
    per = [dict(**row, baseline_loss=float(lb[j]), tuned_loss=float(lt[j]),
                change_pct=100.0 * float(rel[j]),
                baseline_rms_deg=float(b.pos_rms_deg[j]),
                tuned_rms_deg=float(t.pos_rms_deg[j]),
                baseline_static_deg=float(b.theta_ss_deg[j]),
                tuned_static_deg=float(t.theta_ss_deg[j]))
           for j, row in enumerate(rows)]
    j = int(np.argmax(rel))
    worst = dict(per[j]) if rel[j] > tol else None
    return dict(n=len(per), improved=int(np.sum(rel < -tol)), worse=int(np.sum(rel > tol)),
                unchanged=int(np.sum(np.abs(rel) <= tol)), tolerance_pct=100.0 * tol,
                worst_regression=worst,
                best_improvement_pct=100.0 * float(np.min(rel)),
                rms_worse=int(np.sum(np.asarray(t.pos_rms_deg) >
                                     (1 + tol) * np.asarray(b.pos_rms_deg))),
                worst_rms_change_pct=100.0 * float(np.max(
                    np.asarray(t.pos_rms_deg) / np.maximum(np.asarray(b.pos_rms_deg), 1e-12)
                    - 1.0)),
                scenarios=per)


def accounting_lines(acc: dict, split: str) -> list[str]:
    """Console lines for one split's accounting."""
    lines = [f"{split}: {acc['improved']} of {acc['n']} scenarios improved, {acc['worse']} "
             f"worse, {acc['unchanged']} within {acc['tolerance_pct']:.0f} % "
             f"(RMS angle error worse in {acc['rms_worse']}, by up to "
             f"{max(acc['worst_rms_change_pct'], 0.0):.0f} %)"]
    w = acc["worst_regression"]
    if w is not None:
        lines.append(
            f"  worst regression {w['change_pct']:+.1f} % at {where(w)} "
            f"(loss {w['baseline_loss']:.3f} -> {w['tuned_loss']:.3f}, RMS "
            f"{w['baseline_rms_deg']:.2f} -> {w['tuned_rms_deg']:.2f} deg)")
    return lines


def where(row: dict) -> str:
    """Where a scenario is, in words: speed, load, and every mismatch factor that is not
    1 (validation runs: the ramp's start speed, R_s, psi_f and the noise factor too)."""
    if "start_pu" in row:
        out = (f"speed {row['start_pu']:g} -> {row['speed_pu']:g} p.u., load step "
               f"{row['load_pu']:g} p.u.")
    else:
        out = f"speed {row['speed_pu']:g} p.u., load {row['load_pu']:g} p.u."
    names = (("k_d", "L_d"), ("k_q", "L_q"), ("k_R", "R_s"), ("k_psi", "psi_f"),
             ("k_noise", "noise"))
    factors = [f"{n} x {row[k]:.3g}" for k, n in names
               if k in row and (k in ("k_d", "k_q") or row[k] != 1.0)]
    return out + ", " + ", ".join(factors)


def verdict(acc: dict, beats: dict, what: str = "robust loss") -> dict:
    """Whether the tuned design beats the baseline: a lower aggregate loss (`what`) on the
    training, held-out and validation scenarios and no scenario of any of them worse
    beyond the accounting's tolerance. `acc`: `{split: accounting}`; `beats`:
    `{split: bool}` (lower aggregate). Returns `{"holds": bool, "where_not": [str, ...]}`."""
    out = []
    for split, a in acc.items():
        if not beats[split]:
            out.append(f"{split}: the {what} is not lower")
        if a["worse"]:
            w = a["worst_regression"]
            out.append(f"{split}: {a['worse']} of {a['n']} scenarios worse by more than "
                       f"{a['tolerance_pct']:g} %, the worst {w['change_pct']:+.1f} % at "
                       f"{where(w)}")
    return dict(holds=not out, where_not=out)


def summary(report: TuningReport) -> dict:
    """The content of summary.json (plain Python types)."""
    cfg = report.config
    L = report.losses
    res = report.results["tuned"]
    feas_all = report.all_feasible("tuned")
    desc = descriptions(report.designs["paper"])
    beats = {k: L["tuned"][k] < L["paper"][k] for k in SPLITS}
    acc = {split: accounting(report, split) for split in SPLITS}
    out = dict(
        motor=cfg.motor, observer=cfg.observer,
        observer_class=cfg.observer_class().__name__, parametrisation=cfg.design_kind,
        tuned_parameters=list(cfg.tuned), baseline_label=report.label,
        optimiser=cfg.optimiser, objective=cfg.objective,
        baseline_loss=L["paper"]["train"], tuned_loss=L["tuned"]["train"],
        heldout_baseline_loss=L["paper"]["heldout"],
        heldout_tuned_loss=L["tuned"]["heldout"],
        validation_baseline_loss=L["paper"]["validation"],
        validation_tuned_loss=L["tuned"]["validation"],
        improvement_pct={k: report.improvement_pct(k) for k in SPLITS},
        beats_baseline=beats,
        verdict=verdict(acc, beats, f"{report_objective(cfg)} loss"),
        feasible=feas_all,
        feasible_per_scenario=dict(
            train=report.feasibility["tuned"]["train"]["feasible"],
            heldout=report.feasibility["tuned"]["heldout"]["feasible"]),
        baseline_feasible=report.all_feasible("paper"),
        loss_history=res.stats["loss"], best_loss_history=res.stats["best"],
        n_simulations_history=res.stats["n_simulations"],
        optimiser_wall_time_history_s=res.stats["wall_time_s"],
        optimiser_result=res.result,
        wall_time_s=report.wall_time_s, timings_s=report.timings,
        compile_time_s={k: r.stats["compile_time_s"] for k, r in report.results.items()},
        designs={k: dict(description=desc[k], train_loss=L[k]["train"],
                         heldout_loss=L[k]["heldout"],
                         validation_loss=L[k]["validation"],
                         feasible=report.all_feasible(k))
                 for k in report.designs},
        tuned_design=tuned_design(report),
        scenarios=dict(train=_scenario_rows(report, "train"),
                       heldout=_scenario_rows(report, "heldout"),
                       validation=_validation_rows(report)),
        accounting=acc,
        benchmark=targets_reached(report.results, _start_objective(report)),
        histories={k: dict(loss=r.stats["loss"], best=r.stats["best"],
                           n_simulations=r.stats["n_simulations"],
                           wall_time_s=r.stats["wall_time_s"],
                           wall_time_warm_s=r.stats["wall_time_warm_s"], result=r.result)
                   for k, r in report.results.items()},
        config=cfg.to_dict(),
        files=dict(schedule=SCHEDULE_FILE, plots=list(PLOTS), motor=MOTOR_FILE,
                   gains_table=dict(pj.GAINS_TABLE_FILES)),
        notes=[
            "Losses (baseline_loss, tuned_loss, designs) are the robust aggregate "
            "(smooth maximum over scenarios, log-mean-exp at `temperature`; the mean for "
            "objective 'average') of the per-scenario loss w_pos*RMS angle error after "
            "t_transient (deg) + w_settle*settling surrogate/settle_unit + "
            "w_noise*speed-estimate noise std/noise_unit + w_stab*stability penalty, for "
            "either objective. The optimiser histories (loss_history, histories, "
            "benchmark) are the objective the optimiser minimised: for 'no_regression' "
            "the robust aggregate plus the penalty on training scenarios whose loss "
            "exceeds the baseline's by more than regression_tol/2 (relative); only "
            "designs with no training scenario worse than regression_tol can be the best.",
            "feasible: for every training and held-out scenario, the exact analysis "
            "(pmsmjax.analysis.equilibria_traced over the observer's error_rhs, or the "
            "family's own route observer.fast_equilibria, on the grid n_grid, at the "
            "scenario's operating point with the mismatched observer model) finds the "
            "designed equilibrium stable (Hurwitz) and no other stable equilibrium.",
            "The held-out grid uses inductance factors not in the training grid and other "
            "noise keys; it is not used during tuning.",
            "The validation runs (tuning.validation) are closed-loop, speed-controlled "
            "sensorless runs (speed ramp, load step) at speeds off the training speeds, "
            "both directions, with mismatch in L_d, L_q, R_s, psi_f and more current "
            "noise; never used during tuning. Their loss is w_pos*RMS angle error over the "
            "run (deg) + w_noise*speed-estimate noise after the load step/noise_unit.",
            "verdict: the tuned design beats the baseline only if its objective is lower "
            "on the training, held-out and validation scenarios and no scenario of any "
            "of them got worse by more than the accounting's tolerance; where_not lists "
            "what fails.",
        ],
    )
    return _clean(out)


def _start_objective(report: TuningReport) -> float:
    """The objective the optimisers minimised, at the paper's design (their start: the
    first evaluation of the tuner)."""
    return float(report.results["tuned"].stats["loss"][0])


def _validation_rows(report: TuningReport) -> list:
    rows = []
    for j, row in enumerate(report.validation.table()):
        for name in report.designs:
            m = report.metrics[name]["validation"]
            row[name] = dict(
                loss=float(m.loss[j]), pos_rms_deg=float(m.pos_rms_deg[j]),
                theta_ss_deg=float(m.theta_ss_deg[j]), noise_rad_s=float(m.noise_rad_s[j]),
                w_bias_rad_s=float(m.w_bias_rad_s[j]), ok=bool(m.ok[j]))
        rows.append(row)
    return rows


_SCHEDULE_UNITS = dict(zeta1="-", ratio="w1/|w0|", zeta2="-", w2="rad/s",
                      nu2="x min-norm |g2|", nu3="x min-norm |g3|", w1_rad_s="rad/s")


def tuned_design(report: TuningReport) -> dict:
    """The tuned design for summary.json: its parametrisation, the tuned quantities, and
    the physical values (`AbstractDesign.table`; for a `GainSchedule` at its nodes
    (`nodes`) and at every speed of the problem (`at_speeds`))."""
    cfg = report.config
    d = report.tuned
    out = dict(parametrisation=d.kind, observer=cfg.observer,
               tuned_quantities=list(cfg.tuned))
    if isinstance(d, GainSchedule):
        speeds = sorted(set(cfg.speeds_pu) | set(cfg.nodes_pu))
        out.update(nodes=d.table(), at_speeds=d.table(speeds), units=_SCHEDULE_UNITS)
    else:
        out.update(d.table())
    return out


def write_report(report: TuningReport, out, *, plot: bool = True) -> dict:
    """Write summary.json, the tuned schedule and (if `plot`) the plots into `out`."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    eqx.tree_serialise_leaves(out / SCHEDULE_FILE, report.tuned)
    s = summary(report)
    # deployment: the tuned gains as a lookup table (with the sampling period, objective
    # and verdict), and the drive they were tuned for
    verdict = dict(s["verdict"], baseline=s["baseline_label"])
    pj.write_gains_table(gains_table(report.tuned, report.config, verdict=verdict), out)
    pj.save_motor_file(report.config.drive(), out / MOTOR_FILE)
    (out / SUMMARY_FILE).write_text(json.dumps(s, indent=1, allow_nan=False))
    if plot:
        plot_report(report, out)
    return s


def config_from_summary(summary_or_dir) -> TuningConfig:
    """The `TuningConfig` stored in a summary.json (a dict, a file or its folder)."""
    s = summary_or_dir
    if not isinstance(s, dict):
        p = pathlib.Path(s)
        p = p / SUMMARY_FILE if p.is_dir() else p
        s = json.loads(p.read_text())
    c = dict(s["config"])
    moved = c.get("motor_file") and not pathlib.Path(c["motor_file"]).is_file()
    if moved and not isinstance(summary_or_dir, dict):  # the folder's copy of the drive
        c["motor_file"], c["set_params"] = str(p.parent / MOTOR_FILE), ()
    c["bounds"] = {n: tuple(b) for n, b in c["bounds"].items()}
    for k, v in c.items():
        if isinstance(v, list):
            c[k] = tuple(v)
    return TuningConfig(**c)


def load_schedule(out) -> AbstractDesign:
    """The tuned design saved in the output folder `out` (bit-identical): a
    `GainSchedule` or a `ConstantDesign`, as `config_from_summary(out).initial_schedule()`."""
    out = pathlib.Path(out)
    like = config_from_summary(out).initial_schedule()
    return eqx.tree_deserialise_leaves(out / SCHEDULE_FILE, like)


# ---------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------

_LABELS = {"tuned": "tuned", "min_norm_25": "tuned, min-norm (25)",
           "random_search": "random search", "local_search": "(1+1) local search"}


def _label(report, name):
    return report.label if name == "paper" else _LABELS.get(name, name)
_COLORS = {"tuned": "C0", "min_norm_25": "C2", "random_search": "C1", "local_search": "C4"}


def report_figures(report: TuningReport) -> dict:
    """The report's matplotlib figures `{file name: Figure}`: the loss curves, the
    error-versus-mismatch heat maps before/after and the time trace."""
    import matplotlib.pyplot as plt

    return {name: fn(report, plt) for name, fn in (
        ("loss_curve.png", _plot_loss), ("heatmaps.png", _plot_heatmaps),
        ("time_trace.png", _plot_trace), ("per_scenario.png", _plot_per_scenario))}


def plot_report(report: TuningReport, out) -> None:
    """Save `report_figures` into the folder `out` (and close them)."""
    import matplotlib.pyplot as plt

    out = pathlib.Path(out)
    for name, fig in report_figures(report).items():
        fig.savefig(out / name, dpi=110)
        plt.close(fig)


def _plot_loss(report, plt):
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    base = _start_objective(report)
    for name, r in report.results.items():
        s = r.stats
        kw = dict(label=_label(report, name), color=_COLORS.get(name))
        if name in ("tuned", "min_norm_25"):
            axes[0].plot(np.arange(1, s["steps"] + 1), s["loss"], alpha=0.35, lw=1,
                         color=_COLORS.get(name))
        axes[0].plot(np.arange(1, s["steps"] + 1), s["best"], **kw)
        axes[1].plot(s["wall_time_warm_s"], s["best"], **kw)
    for ax in axes:
        ax.axhline(base, color="k", ls="--", lw=1, label=report.label)
        ax.set_ylabel(f"{report.config.objective} objective (best so far)")
        ax.grid(alpha=0.3)
    axes[0].set_xlabel(f"evaluation (x {report.train.n} simulations)")
    axes[1].set_xlabel("wall time without compilation (s)")
    axes[0].legend()
    fig.suptitle(f"Design tuning, {report.config.motor}, {report.config.observer.upper()} "
                 f"({report.config.design_kind}: {', '.join(report.config.tuned)}): "
                 f"training objective", fontsize=10)
    fig.tight_layout()
    return fig


def _grid(report, split, name, field):
    scen = report.train if split == "train" else report.heldout
    kd, kq = np.asarray(scen.k_d), np.asarray(scen.k_q)
    vals = np.asarray(getattr(report.metrics[name][split], field))
    ud, uq = np.unique(kd), np.unique(kq)
    grid = np.full((uq.size, ud.size), -np.inf)
    for a, b, v in zip(kd, kq, vals):  # worst case over the operating points
        i, j = np.searchsorted(uq, b), np.searchsorted(ud, a)
        grid[i, j] = max(grid[i, j], v)
    return ud, uq, grid


def _plot_heatmaps(report, plt):
    cols = [("train", "loss", "training: scenario loss"),
            ("heldout", "loss", "held-out: scenario loss"),
            ("heldout", "pos_rms_deg", "held-out: RMS angle error (deg)")]
    names = ("paper", "tuned")
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    for c, (split, field, title) in enumerate(cols):
        grids = [_grid(report, split, n, field) for n in names]
        vmax = max(np.max(g[2]) for g in grids)
        vmin = min(np.min(g[2]) for g in grids)
        for r, (n, (ud, uq, g)) in enumerate(zip(names, grids)):
            ax = axes[r, c]
            im = ax.imshow(g, origin="lower", cmap="viridis", vmin=vmin, vmax=vmax,
                           aspect="auto")
            ax.set_xticks(range(ud.size), [f"{v:.3g}" for v in ud])
            ax.set_yticks(range(uq.size), [f"{v:.3g}" for v in uq])
            for i in range(uq.size):
                for j in range(ud.size):
                    ax.text(j, i, f"{g[i, j]:.2f}", ha="center", va="center", fontsize=7,
                            color="w" if g[i, j] < 0.5 * (vmin + vmax) else "k")
            ax.set_xlabel("$\\hat L_d / L_d$")
            ax.set_ylabel("$\\hat L_q / L_q$")
            ax.set_title(f"{_label(report, n)}: {title}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"{report.config.observer.upper()}: worst case over the operating points "
                 f"(speeds x loads) per inductance mismatch")
    fig.tight_layout()
    return fig


def _mismatch(row):
    return max(abs(row[k] - 1) for k in ("k_d", "k_q", "k_R", "k_psi") if k in row)


def _plot_per_scenario(report, plt):
    """Tuned vs baseline loss per scenario (left) and the relative change per scenario
    against the speed, coloured by the model mismatch (right); training, held-out and
    validation scenarios."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    lim = 0.0
    accs = {split: accounting(report, split) for split in SPLITS}
    mis_max = max(_mismatch(r) for a in accs.values() for r in a["scenarios"])
    for split, marker in (("train", "o"), ("heldout", "s"), ("validation", "^")):
        acc = accs[split]
        lb = np.array([r["baseline_loss"] for r in acc["scenarios"]])
        lt = np.array([r["tuned_loss"] for r in acc["scenarios"]])
        lim = max(lim, lb.max(), lt.max())
        worse = lt > (1 + acc["tolerance_pct"] / 100) * lb
        axes[0].scatter(lb[~worse], lt[~worse], marker=marker, s=18, color="C0", alpha=0.7,
                        label=f"{split}: better or equal ({(~worse).sum()})")
        axes[0].scatter(lb[worse], lt[worse], marker=marker, s=24, color="C3",
                        label=f"{split}: worse ({worse.sum()})")
        sp = np.array([r["speed_pu"] for r in acc["scenarios"]])
        mis = np.array([_mismatch(r) for r in acc["scenarios"]])
        ch = np.array([r["change_pct"] for r in acc["scenarios"]])
        sc = axes[1].scatter(sp, ch, c=mis, marker=marker, s=20, cmap="viridis",
                             vmin=0.0, vmax=max(mis_max, 1e-9), label=split)
    axes[0].plot([0, lim], [0, lim], "k--", lw=0.8)
    axes[0].set_xscale("log")
    axes[0].set_yscale("log")
    axes[0].set_xlabel(f"{report.label} loss per scenario")
    axes[0].set_ylabel("tuned loss per scenario")
    axes[0].legend(fontsize=8)
    axes[1].axhline(0.0, color="k", lw=0.8)
    axes[1].set_xlabel("speed (p.u.)")
    axes[1].set_ylabel("change of the scenario loss (%)")
    axes[1].legend(fontsize=8)
    fig.colorbar(sc, ax=axes[1], label="largest |model factor - 1| (L_d, L_q, R_s, psi_f)")
    fig.suptitle("Per-scenario change, tuned vs " + report.label)
    fig.tight_layout()
    return fig


def _plot_trace(report, plt):
    tr = report.traces
    sc = tr["scenario"]
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    t = 1e3 * np.asarray(tr["t"])
    for name, color in (("paper", "C3"), ("tuned", "C0")):
        if name not in tr:
            continue
        lab = _label(report, name)
        axes[0].plot(t, tr[name]["theta_err_deg"], color=color, lw=1, label=lab)
        axes[1].plot(t, tr[name]["w_err"], color=color, lw=0.8, label=lab)
    axes[0].set_ylabel("angle error $\\theta - \\hat\\theta$ (deg)")
    axes[1].set_ylabel("speed error $\\omega - \\hat\\omega$ (rad/s)")
    axes[1].set_xlabel("t (ms)")
    for ax in axes:
        ax.axvline(1e3 * report.config.t_transient, color="k", ls=":", lw=1)
        ax.grid(alpha=0.3)
        ax.legend()
    axes[0].set_title(
        f"{report.config.observer.upper()}, hardest training scenario for {report.label}: "
        f"L_d x {sc['k_d']:.3g}, L_q x {sc['k_q']:.3g}, {sc['speed_pu']:.3g} p.u. speed, "
        f"{sc['load_pu']:.3g} p.u. load", fontsize=10)
    fig.tight_layout()
    return fig
