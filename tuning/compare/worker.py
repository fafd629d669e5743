"""Worker process of `python -m tuning compare --jobs N` (`tuning.compare._run_workers`):
computes one observer's part of the comparison in the job folder `--out`, whose
`job.json` holds the configuration, and writes `OUT/observers/NAME.json`."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import pmsmjax as pj


def main(argv=None) -> int:
    pj.runtime.configure()
    p = argparse.ArgumentParser(prog="python -m tuning.compare.worker")
    p.add_argument("--out", required=True)
    p.add_argument("--observer", required=True)
    p.add_argument("--sweep-dir", required=True)
    p.add_argument("--batch-size", type=int, default=None)
    args = p.parse_args(argv)
    from .config import CompareConfig
    from .job import _Context, _Units, observer_entry

    out = pathlib.Path(args.out)
    config = CompareConfig.from_dict(json.loads((out / "job.json").read_text())["config"])
    grid = config.grid(index=True)
    ctx = _Context(config, out, pathlib.Path(args.sweep_dir), grid, False, print,
                   args.batch_size)
    observer_entry(ctx, args.observer, _Units())
    return 0


if __name__ == "__main__":
    sys.exit(main())
