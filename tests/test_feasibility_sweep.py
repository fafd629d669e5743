"""`pmsmjax feasibility` through the sweep runner: an interrupted map resumes to the same
files as an uninterrupted one, --restart and another map in the same --sweep-dir, and
the two-process example (`examples/distributed_feasibility.sh`, jax.distributed on one
machine) gives the single-process map bit for bit."""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from pmsmjax import analysis
from pmsmjax.cli import main


REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SALIENT = ["--observer", "leso", "--set", "L_d=1e-3", "--set", "L_q=4.9e-3", "--i-q", "2"]
# 2 speeds x 11 x 9 = 198 designs: 5 chunks of 40 (the last one 38)
MAP = [*SALIENT, "--zeta1", "0:5:11", "--ratio", "0:2:9", "--speeds", "0.5", "1",
       "--chunk-size", "40"]


def npz(path):
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def assert_same_npz(a, b):
    """Same names, dtypes, shapes and bytes (NaNs included). The .npz files themselves
    are not byte-equal: the zip entries carry the time they were written."""
    a, b = npz(a), npz(b)
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert a[k].tobytes() == b[k].tobytes(), k


class Interrupted(KeyboardInterrupt):
    pass


def test_interrupted_map_resumes_to_the_same_files(tmp_path, monkeypatch, capsys):
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert main(["feasibility", *MAP, "--out", str(full)]) == 0
    assert "5 chunks of up to 40 points on 1 device in 1 process;" in capsys.readouterr().out

    # Ctrl-C after the second chunk: the run stops, the finished chunks stay on disk
    run_sweep = analysis.run_sweep

    def stop_after_two(*args, on_chunk_done, **kw):
        def done(info):
            on_chunk_done(info)
            if info.index == 1:
                raise Interrupted

        return run_sweep(*args, on_chunk_done=done, **kw)

    monkeypatch.setattr(analysis, "run_sweep", stop_after_two)
    with pytest.raises(Interrupted):
        main(["feasibility", *MAP, "--out", str(cut)])
    monkeypatch.undo()
    assert sorted(os.listdir(cut)) == ["sweep"]  # no half-written outputs
    assert sorted(p.name for p in (cut / "sweep").glob("chunk_*.npz")) == [
        "chunk_000000.npz", "chunk_000001.npz"]
    assert not json.loads((cut / "sweep" / "sweep.json").read_text())["complete"]
    mtimes = {p.name: p.stat().st_mtime_ns for p in (cut / "sweep").glob("chunk_*")}

    # the same command again: resumes (reuses 2 chunks), the files are the same
    capsys.readouterr()
    assert main(["feasibility", *MAP, "--out", str(cut)]) == 0
    assert "2 reused from an earlier run" in capsys.readouterr().out
    for name, t in mtimes.items():
        assert (cut / "sweep" / name).stat().st_mtime_ns == t  # not computed again
    assert_same_npz(cut / "feasibility.npz", full / "feasibility.npz")
    assert (cut / "feasibility.png").read_bytes() == (full / "feasibility.png").read_bytes()
    # the command's file holds the map: neither sweep keeps a result.npz
    assert not (cut / "sweep" / "result.npz").exists()
    assert not (full / "sweep" / "result.npz").exists()
    for i in range(5):
        name = f"chunk_{i:06d}.npz"
        assert_same_npz(cut / "sweep" / name, full / "sweep" / name)
    a, b = (json.loads((d / "sweep" / "sweep.json").read_text()) for d in (cut, full))
    assert a["fingerprint"] == b["fingerprint"] and a["complete"] and b["complete"]
    assert a["metadata"]["command"] == "pmsmjax feasibility"

    # another map in the same --sweep-dir: a finished sweep there is replaced (as the
    # command's outputs are), an unfinished one refused, naming the ways out
    assert main(["feasibility", *MAP, "--ratio", "0:2:5", "--no-plot", "--out", str(cut)]) == 0
    assert "replacing the finished sweep of other inputs" in capsys.readouterr().out
    monkeypatch.setattr(analysis, "run_sweep", stop_after_two)
    with pytest.raises(Interrupted):
        main(["feasibility", *MAP, "--out", str(cut)])
    monkeypatch.undo()
    capsys.readouterr()
    assert main(["feasibility", *MAP, "--ratio", "0:2:5", "--out", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "--sweep-dir" in err and "different sweep" in err and "--restart" in err
    # --restart discards the finished chunks and computes everything again
    assert main(["feasibility", *MAP, "--restart", "--no-plot", "--out", str(cut)]) == 0
    assert "reused" not in capsys.readouterr().out
    assert_same_npz(cut / "feasibility.npz", full / "feasibility.npz")


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_two_processes_give_the_single_process_map(tmp_path):
    """`examples/distributed_feasibility.sh`: two `pmsmjax feasibility` processes with
    jax.distributed on this machine (one CPU device each). With --batch-size the per-point
    code is the same on any number of devices, so the map equals the one-process map bit
    for bit."""
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)  # one CPU device per process (the script sets JAX_PLATFORMS)
    env["PMSMJAX"] = f"{sys.executable} -m pmsmjax"
    env["PYTHONPATH"] = REPO + os.pathsep + env.get("PYTHONPATH", "")
    two = tmp_path / "two"
    proc = subprocess.run(
        ["sh", os.path.join(REPO, "examples", "distributed_feasibility.sh"), str(two),
         str(_free_port()), "--", "--zeta1", "0:5:21", "--ratio", "0:2:11", "--no-plot"],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "process 1 of 2 done" in proc.stdout
    assert "on 2 devices in 2 processes" in proc.stdout
    manifest = json.loads((two / "sweep" / "sweep.json").read_text())
    assert manifest["devices"]["count"] == 2 and manifest["complete"]

    one = tmp_path / "one"
    assert main(["feasibility", *SALIENT, "--zeta1", "0:5:21", "--ratio", "0:2:11",
                 "--speed", "0.5", "--chunk-size", "512", "--batch-size", "64",
                 "--no-plot", "--out", str(one)]) == 0
    assert_same_npz(two / "feasibility.npz", one / "feasibility.npz")
    st = npz(one / "feasibility.npz")["status"]
    assert {0, 1, -1} <= set(np.unique(st))  # feasible, infeasible and degenerate designs


def test_a_map_reuses_only_its_own_compiled_function():
    """Maps computed again in one process reuse their per-point function (and so its
    compiled code) only when everything it closes over is the same."""
    from pmsmjax.cli import current_from_args, drive_from_args, observer_from_args
    from pmsmjax.cli.__main__ import build_parser
    from pmsmjax.cli._feasibility import _point_key

    def key(*argv):
        args = build_parser().parse_args(["feasibility", *argv])
        drive = drive_from_args(args)
        choice = observer_from_args(args, drive, skip=("zeta1", "ratio"))
        i_pu, _ = current_from_args(args, drive)
        return _point_key(choice, drive, "zeta1", "ratio", i_pu)

    base = key(*SALIENT)
    assert key(*SALIENT, "--zeta1", "0:1:3", "--chunk-size", "7") == base  # grid, chunks
    others = [key(*SALIENT[:-2], "--i-q", "1"), key("--i-q", "2"),
              key(*SALIENT, "--set", "psi_f=0.05"), key(*SALIENT, "--zeta2", "0.8"),
              key(*SALIENT, "--mismatch", "R_s=1.2"), key(*SALIENT, "--observer", "eso")]
    assert len({base, *others}) == 1 + len(others)
