"""Regenerate `docs/figures/tuning.png`, the first figure of the tuning page: the default
job (`python -m tuning`: zhang2022's ESO on zhang750) run through the public API, and
two of the figures its report writes side by side (a few minutes on 2 cores):

- `search.png`: the searches at equal budget, best training objective against
  closed-loop simulations, the paper design's objective dotted;
- `validation.png`: the verdict's evidence, each validation run's RMS angle error, paper
  design against the deployed design, with the rule's +tolerance line.

    .venv/bin/python docs/figures/make_tuning_figure.py   # the job's folder: results/tuning-docs
"""

import pathlib

import matplotlib

import pmsmjax as pj
import tuning


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent
OUT = pathlib.Path("results/tuning-docs")

if __name__ == "__main__":
    pj.runtime.configure()
    report = tuning.tune(tuning.TuningProblem())
    tuning.write_report(report, OUT)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    for ax, name in zip(axes, ("search.png", "validation.png")):
        ax.imshow(plt.imread(OUT / name))
        ax.set_axis_off()
    fig.tight_layout(pad=0.2)
    fig.savefig(HERE / "tuning.png", dpi=150)
    acc = tuning.summary(report)["accounting"]["validation"]
    print(f"verdict holds: {report.verdict['holds']}; validation: {acc}")
    print(f"wrote {HERE / 'tuning.png'}")
