"""Regenerate `docs/figures/comparison_maps.png`, the README's figure of the observer
comparison: one observer of each paper on zhang750, paper designs, a small grid (about a
minute; the job folder is resumable, so a finished one is reused), and copies its
robustness maps here.

    .venv/bin/python docs/figures/make_comparison_figure.py [--out results/compare-readme]
"""

import argparse
import pathlib
import shutil

import pmsmjax as pj
import tuning


HERE = pathlib.Path(__file__).resolve().parent

if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--out", default="results/compare-readme")
    args = p.parse_args()
    pj.runtime.configure()
    config = tuning.CompareConfig(
        motor="zhang750", observers=("eso", "parallel-model", "rotor-flux", "fa-leso"),
        T_s=250e-6, t_end=0.2, speeds_pu=(0.1, 1.0), loads_pu=(0.0, 1.0),
        cases=((1.0, 1.0, 1.0, 1.0), (0.7, 1.3, 1.0, 1.0), (1.0, 1.0, 1.5, 1.0),
               (1.0, 1.0, 1.0, 0.85)),
        tuner="none", analysis=False, harmonic_speeds_pu=(0.5,))
    tuning.run_comparison(config, args.out, progress=False, plot=True)
    shutil.copyfile(pathlib.Path(args.out) / "robustness_maps.png",
                    HERE / "comparison_maps.png")
    print(f"wrote {HERE / 'comparison_maps.png'}")
