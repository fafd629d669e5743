"""Regenerate `docs/figures/comparison_quick_maps.png`, the README's figure of the observer
comparison: runs `python -m tuning compare --quick` (every observer on zhang750; resumable,
so a finished job folder is reused) and copies its robustness maps here.

    .venv/bin/python docs/figures/make_comparison_figure.py [--out results/compare-quick]
"""

import argparse
import pathlib
import shutil
import sys

from tuning.__main__ import main


HERE = pathlib.Path(__file__).resolve().parent

if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--out", default="results/compare-quick")
    args = p.parse_args()
    rc = main(["compare", "--quick", "--out", args.out, "--no-progress"])
    if rc:
        sys.exit(rc)
    shutil.copyfile(pathlib.Path(args.out) / "robustness_maps.png",
                    HERE / "comparison_quick_maps.png")
    print(f"wrote {HERE / 'comparison_quick_maps.png'}")
