"""The report's figures (matplotlib, written as PNG), each titled with the metric a user
reads first, the RMS angle error of the paper's and the deployed design on the validation
runs (deg, mean over the runs):

- `search.png`: best training objective (dimensionless, not degrees) against closed-loop
  simulations, every strategy at the same budget;
- `front.png`: the tracking-versus-noise front on the validation runs (mean RMS angle
  error against mean speed-estimate noise), the paper design and the default marked;
- `validation.png`: each validation run's RMS angle error, paper design against the
  default, with the +tolerance line; the verdict as counted in its title.
"""

from __future__ import annotations

import pathlib
import textwrap

import numpy as np


PLOTS = ("search.png", "front.png", "validation.png")


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
