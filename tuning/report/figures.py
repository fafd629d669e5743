"""The report's figures (matplotlib, written as PNG), each titled with the metric a user
reads first, the RMS angle error of the paper's and the deployed design on the validation
runs (deg, mean over the runs):

- `search.png`: best training objective (dimensionless, not degrees) against closed-loop
  simulations, every strategy at the same budget;
- `front.png`: the tracking-versus-noise front on the validation runs (mean RMS angle
  error against mean speed-estimate noise), the paper design and the default marked;
- `validation.png`: each validation run's RMS angle error, paper design against the
  default, with the +tolerance line; the verdict as counted in its title;
- `blocking.png` (`BLOCKING_PLOT`, only where validation runs block the verdict: worse
  by more than the tolerance, or newly losing lock): the worst of them over time, the
  paper's design against the tuned one, its phases shaded with each phase's share of the change
  (`TuningReport.blocking_trace`, `tuning.phase_split`).
"""

from __future__ import annotations

import pathlib
import textwrap

import numpy as np


PLOTS = ("search.png", "front.png", "validation.png")
#: The figure of the worst blocking run, written only where there is one.
BLOCKING_PLOT = "blocking.png"


def plot_report(report, out) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = pathlib.Path(out)
    acc = report.accounting["validation"][report.default]
    rms = (f"RMS angle error (validation, mean): paper {acc['mean_rms_deg_reference']:.2f}"
           f" deg -> {report.default} {acc['mean_rms_deg']:.2f} deg")
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in report.searches.items():
        if name.startswith("front"):
            continue
        h = np.asarray(r.history)
        ax.plot(h[:, 0], h[:, 1], label=f"{name} ({r.wall_s:.0f} s)")
    ax.axhline(report.objective["train"]["paper"], color="k", ls=":", label="paper design")
    ax.set_xlabel("closed-loop simulations")
    ax.set_ylabel("training objective, best so far (dimensionless)")
    ax.set_title(f"{report.problem.observer}: searches at equal budget\n{rms}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "search.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    mv = report.metrics["validation"]
    for name, m in mv.items():
        if name == "paper-perturbed":
            continue
        x = float(np.mean(np.asarray(m.noise_rad_s)))
        y = float(np.mean(np.asarray(m.rms_deg)))
        mk = "*" if name == report.default else ("s" if name == "paper" else "o")
        ax.plot(x, y, mk, ms=12 if mk == "*" else 7, label=name)
    ax.set_xlabel("speed-estimate noise, mean over validation runs (rad/s)")
    ax.set_ylabel("RMS angle error, mean over validation runs (deg)")
    ax.set_title(f"tracking versus noise (validation)\n{rms}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "front.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ref = np.asarray(mv["paper"].rms_deg)
    new = np.asarray(mv[report.default].rms_deg)
    ax.loglog(ref, new, "o", ms=4)
    lim = [min(ref.min(), new.min()) * 0.8, max(ref.max(), new.max()) * 1.2]
    ax.plot(lim, lim, "k-", lw=0.8, label="equal")
    tol = report.problem.regression_tol
    ax.plot(lim, [v * (1 + tol) for v in lim], "r:", lw=0.8,
            label=f"+{100 * tol:g} % (the rule)")
    ax.set_xlabel("paper design: RMS angle error (deg)")
    ax.set_ylabel(f"{report.default}: RMS angle error (deg)")
    verdict = textwrap.wrap(f"verdict {report.verdict['statement']}", 80)
    ax.set_title("\n".join([rms, *verdict]), fontsize=8)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "validation.png", dpi=120)
    plt.close(fig)
    if report.blocking_trace is not None:
        _plot_blocking(plt, report.blocking_trace, out / BLOCKING_PLOT)


def _plot_blocking(plt, tr: dict, path) -> None:
    """The worst blocking run over time (`TuningReport.blocking_trace`)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    t = np.asarray(tr["t_s"])
    starts = [*np.asarray(tr["phase_start_s"]), t[-1]]
    for k, (name, ph) in enumerate(tr["phases"].items()):
        lo, hi = max(starts[k], t[0]), min(starts[k + 1], t[-1])
        if hi <= lo:
            continue
        ax.axvspan(lo, hi, color="0.92" if k % 2 else "white", zorder=0)
        ax.text(0.5 * (lo + hi), 1.0, f"{name}\n{ph['share_of_change_pct']:.0f} %",
                transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=7)
    for name, style in (("paper", dict(color="k", lw=0.8)),
                        ("tuned", dict(color="C3", lw=0.8, alpha=0.8))):
        ax.plot(t, np.abs(np.asarray(tr["error_deg"][name])), label=(
            f"{name}: RMS {tr['rms_deg'][name]:.2f} deg"), **style)
    c = tr["case"]
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|angle error| (deg)")
    peak = max(float(np.max(np.abs(np.asarray(e)))) for e in tr["error_deg"].values())
    ax.set_ylim(0, 1.3 * peak if peak > 0 else 1.0)  # room for the phases' labels
    ax.set_title(f"worst blocking run: speed {c['s0']:+g} -> {c['s1']:+g} p.u., model L_d "
                 f"x{c['k_d']:g}, L_q x{c['k_q']:g}, R_s x{c['k_R']:g}, psi_f x{c['k_psi']:g}"
                 f", noise x{c['k_noise']:g}\nRMS {tr['rms_change_pct']:+.1f} % (its noise "
                 f"floor {tr['noise_floor_pct']:.1f} %); per phase: share of the mean-square "
                 f"change", fontsize=8)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2,
              frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
