"""The trade the LESO and the AFO meet over +-50 % (docs/tuning.md, "Inductance mismatch
up to +-50 %"): each observer tuned with the 5 % rule on `TuningProblem.wide_mismatch`,
and per validation case the RMS angle error change of the deployed design and of each
search's design against the paper's (mean over the case's eight runs), the cases grouped
by the observer model's inductance error: right, too high, too low, crossed.

Writes docs/figures/inductance_trade.png and .json (`--from-json`: the figure from the
saved JSON). About 4 minutes on a 2-core machine:

    .venv/bin/python docs/figures/make_inductance_trade_figure.py
"""

import argparse
import json
import os

import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import tuning as tg  # noqa: E402


HERE = os.path.dirname(os.path.abspath(__file__))
OBSERVERS = ("leso", "afo")
DESIGNS = ("tuned", "gradient", "cmaes", "local")
GROUPS = {"right": "#4a4a4a", "too high": "#2a7ab9", "too low": "#c8452c",
          "crossed": "#9a6fb0"}


def group(k_d: float, k_q: float) -> str:
    """The observer model's inductance error of a validation case."""
    if k_d == 1 and k_q == 1:
        return "right"
    if k_d <= 1 and k_q <= 1:
        return "too low"
    if k_d >= 1 and k_q >= 1:
        return "too high"
    return "crossed"


def measure(observer: str) -> dict:
    rep = tg.tune(tg.TuningProblem.wide_mismatch(observer=observer, regression_tol=0.05),
                  progress=False, log=None)
    rows = rep.sets["validation"].table()
    m = rep.metrics["validation"]
    ref = np.asarray(m["paper"].rms_deg)
    cases: dict[tuple, list[int]] = {}
    for j, r in enumerate(rows):
        cases.setdefault(tuple(r[k] for k in ("k_d", "k_q", "k_R", "k_psi", "k_noise")),
                         []).append(j)
    out = {"statement": rep.verdict["statement"], "cases": []}
    for case, idx in cases.items():
        change = {d: float(100 * np.mean(np.asarray(m[d].rms_deg)[idx] / ref[idx] - 1))
                  for d in DESIGNS}
        worst = {d: float(100 * np.max(np.asarray(m[d].rms_deg)[idx] / ref[idx] - 1))
                 for d in DESIGNS}
        out["cases"].append({"case": case, "group": group(case[0], case[1]),
                             "mean_rms_change_pct": change, "worst_rms_change_pct": worst})
    return out


#: The figure's range of RMS changes (%); a case beyond it is drawn at the edge.
YLIM = (-30.0, 20.0)


def label(case) -> str:
    """A validation case's tick: its k_d, k_q, and what else is off."""
    k_d, k_q, k_R, k_psi, k_noise = case
    other = [(n, v) for n, v in (("R_s", k_R), ("psi_f", k_psi), ("noise", k_noise))
             if v != 1]
    text = ", ".join(f"{n} x{v:g}" if len(other) == 1 else n for n, v in other)
    return f"{k_d:g}, {k_q:g}" + (f" ({text} off)" if len(other) > 1 else
                                  f" ({text})" if other else "")


def plot(data: dict, path: str) -> None:
    fig, axes = plt.subplots(1, len(data), figsize=(11, 5.2), sharey=True)
    for ax, (observer, d) in zip(np.atleast_1d(axes), data.items()):
        cases = sorted(d["cases"], key=lambda c: list(GROUPS).index(c["group"]))
        x = np.arange(len(cases))
        for k, name in enumerate(DESIGNS):
            y = np.array([c["worst_rms_change_pct"][name] for c in cases])
            inside = (y >= YLIM[0]) & (y <= YLIM[1])
            colours = np.array([GROUPS[c["group"]] for c in cases])
            xs = x + (k - 1.5) * 0.12
            ax.scatter(xs[inside], y[inside], s=14 if name != "tuned" else 30,
                       c=colours[inside], marker="o" if name == "tuned" else ".",
                       zorder=3)
            ax.scatter(xs[~inside], np.clip(y[~inside], *YLIM), s=18, c=colours[~inside],
                       marker="v", zorder=3)
        ax.axhline(5, color="red", ls=":", lw=1)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xticks(x, [label(c["case"]) for c in cases], rotation=90, fontsize=7)
        ax.set_ylim(YLIM[0] - 1, YLIM[1] + 1)
        ax.set_title(f"{observer.upper()}: {d['statement'].split(':')[0]}", fontsize=10)
        ax.set_xlabel("validation case: the observer model's k_d, k_q (and what else is off)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("worst RMS angle error change in the case (%)\n"
                       "against the paper's design")
    handles = [plt.Line2D([], [], ls="", marker="s", color=c, label=f"inductances {g}")
               for g, c in GROUPS.items()]
    handles += [plt.Line2D([], [], ls="", marker="o", color="k", label="deployed design"),
                plt.Line2D([], [], ls="", marker=".", color="k",
                           label="gradient, CMA-ES, local search"),
                plt.Line2D([], [], ls="", marker="v", color="k",
                           label=f"below {YLIM[0]:g} % (drawn at the edge)"),
                plt.Line2D([], [], ls=":", color="red", label="the 5 % rule")]
    fig.legend(handles=handles, loc="upper center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true",
                    help="draw the figure from the saved JSON, measure nothing")
    args = ap.parse_args()
    path = os.path.join(HERE, "inductance_trade.json")
    if args.from_json:
        with open(path) as f:
            data = json.load(f)
    else:
        data = {o: measure(o) for o in OBSERVERS}
        for d in data.values():
            for c in d["cases"]:
                c["case"] = list(c["case"])
        with open(path, "w") as f:
            json.dump(data, f, indent=1)
    plot(data, os.path.join(HERE, "inductance_trade.png"))


if __name__ == "__main__":
    main()
