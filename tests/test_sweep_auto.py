"""The sweep runner's automatic chunk size (`chunk_size=None`) and what it writes: the size
from the measured cost within the memory bound, the files and bytes of a known grid,
resume after an interruption mid-sweep (also without the manifest) to bit-identical
outputs, a finished sweep loaded from `result.npz`, and `pmsmjax feasibility` by default."""

import io
import json
import os

import jax
import numpy as np
import pytest

from pmsmjax.analysis import _sweep, run_sweep
from pmsmjax.cli import main
from tests.test_sweep import assert_bitwise_equal, counting, cpu_mesh, make_grid, sweep_fn


# Bytes of outputs per point of `sweep_fn`: eig 4 complex128, x_end 4 float64, i_q_max
# float64, status int32.
OUT_BYTES = 4 * 16 + 4 * 8 + 8 + 4


def test_auto_chunk_size_from_the_measured_cost():
    f = _sweep._auto_chunk_size
    s = _sweep._AUTO_CHUNK_SECONDS
    # 1e-4 s per point: a chunk of s / 1e-4 points, whole blocks of 1000, and the points
    # shared evenly between the chunks
    n = 1_000_001
    per_chunk = int(s / 1e-4)
    n_chunks = -(-n // per_chunk)
    expected = -(-(-(-n // n_chunks)) // 1000) * 1000
    assert f(n, 1000, 0.1, 8) == expected
    assert -(-n // expected) == n_chunks
    # work shorter than a chunk: one chunk of every point (rounded up to whole blocks)
    assert f(10_000, 100, 1e-6, 8) == 10_000
    assert f(10_001, 100, 1e-6, 8) == 10_100
    # a block longer than the target: one block per chunk
    assert f(10_000, 100, 10 * s, 8) == 100
    # the memory bound: at most _AUTO_CHUNK_BYTES of outputs per chunk
    big = _sweep._AUTO_CHUNK_BYTES // 250_000  # bytes per point: 250,000 points fit
    size = f(10_000_000, 1000, 1e-9, big)
    assert size * big <= _sweep._AUTO_CHUNK_BYTES and size == 250_000


@pytest.fixture
def small_auto(monkeypatch):
    """Blocks of 8 points and chunks bounded by memory to 3 blocks (24 points), whatever
    the measured time: 105 points -> 5 chunks of 24 (the last one 9)."""
    monkeypatch.setattr(_sweep, "_AUTO_BLOCK_PER_DEVICE", 8)
    monkeypatch.setattr(_sweep, "_AUTO_CHUNK_SECONDS", 1e9)
    monkeypatch.setattr(_sweep, "_AUTO_CHUNK_BYTES", 24 * OUT_BYTES)


def npz_bytes(arrays: dict) -> int:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return len(buf.getvalue())


def test_auto_chunks_files_and_bytes(tmp_path, small_auto):
    grid = make_grid()
    counter, infos = [], []
    fn = counting(sweep_fn, counter)
    out = run_sweep(fn, grid, out_dir=tmp_path / "auto", progress=False, mesh=cpu_mesh(),
                    on_chunk_done=infos.append)
    jax.effects_barrier()
    # 4 chunks of 3 blocks and one of 9 points in 2 blocks; the timed block is not redone
    assert [(i.start, i.stop) for i in infos] == [(0, 24), (24, 48), (48, 72), (72, 96),
                                                   (96, 105)]
    assert len(counter) == 4 * 24 + 16
    manifest = json.loads((tmp_path / "auto" / "sweep.json").read_text())
    assert manifest["chunk_size_auto"] and manifest["chunk_size"] == 24
    assert manifest["n_chunks"] == 5 and manifest["block_size"] == 8 and manifest["complete"]
    assert manifest["fingerprint_parts"]["chunk_size"] == "auto"
    # the same block of 8 points, grouped into chunks of 16: the same bits
    ref = run_sweep(sweep_fn, grid, out_dir=tmp_path / "ref", chunk_size=8, progress=False,
                    mesh=cpu_mesh())
    assert_bitwise_equal(out, ref)

    # What stays: the manifest and result.npz (the chunk files were deleted once the
    # result held them): the outputs and the grid, uncompressed, nothing else.
    assert sorted(os.listdir(tmp_path / "auto")) == ["result.npz", "sweep.json"]
    arrays = {**out, **{f"grid/{k}": v.reshape(grid.shape) for k, v in grid.items()},
              "__fingerprint__": np.array(manifest["fingerprint"])}
    size = os.path.getsize(tmp_path / "auto" / "result.npz")
    assert size == npz_bytes(arrays)
    raw = sum(a.nbytes for a in arrays.values())
    assert raw < size < raw + 4096  # stored, not compressed: the data plus zip headers
    # the explicit chunk size keeps its chunk files (as before): 14 of 8 points
    assert len(list((tmp_path / "ref").glob("chunk_*.npz"))) == 14


class Stop(Exception):
    pass


def test_auto_resume_mid_sweep_is_bit_identical(tmp_path, small_auto, monkeypatch):
    grid = make_grid()
    kw = dict(progress=False, mesh=cpu_mesh())
    counter = []
    fn = counting(sweep_fn, counter)  # the same function object in every run
    full = run_sweep(fn, grid, out_dir=tmp_path / "full", **kw)

    def stop_after_two(info):
        if info.index == 1:
            raise Stop

    cut = tmp_path / "cut"
    with pytest.raises(Stop):
        run_sweep(fn, grid, out_dir=cut, on_chunk_done=stop_after_two, **kw)
    assert sorted(p.name for p in cut.glob("chunk_*.npz")) == ["chunk_000000.npz",
                                                                "chunk_000001.npz"]
    assert not (cut / "result.npz").exists()
    manifest = json.loads((cut / "sweep.json").read_text())
    assert not manifest["complete"] and manifest["chunk_size"] == 24
    with np.load(cut / "chunk_000001.npz") as z:  # what resuming needs, and no more
        assert sorted(z.files) == sorted(["eig", "x_end", "i_q_max", "status",
                                          "__fingerprint__", "__metadata__", "__chunk__",
                                          "__start__", "__stop__", "__chunk_size__"])
        assert (int(z["__start__"]), int(z["__stop__"]), int(z["__chunk_size__"])) == \
            (24, 48, 24)

    # The resumed run keeps the first run's chunk size, although it would now choose
    # another (here: 2 blocks), and computes only the missing chunks.
    monkeypatch.setattr(_sweep, "_AUTO_CHUNK_BYTES", 16 * OUT_BYTES)
    jax.effects_barrier()
    counter.clear()
    infos = []
    resumed = run_sweep(fn, grid, out_dir=cut,
                        on_chunk_done=infos.append, **kw)
    jax.effects_barrier()
    assert_bitwise_equal(resumed, full)
    assert [(i.index, i.loaded) for i in infos] == [(0, True), (1, True), (2, False),
                                                    (3, False), (4, False)]
    assert len(counter) == 24 + 24 + 16
    assert sorted(os.listdir(cut)) == ["result.npz", "sweep.json"]
    with np.load(cut / "result.npz") as a, np.load(tmp_path / "full" / "result.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            assert a[k].tobytes() == b[k].tobytes(), k

    # A finished sweep is read from result.npz: nothing computed, nothing written.
    counter.clear()
    infos.clear()
    mtime = os.stat(cut / "result.npz").st_mtime_ns
    again = run_sweep(fn, grid, out_dir=cut,
                      on_chunk_done=infos.append, **kw)
    jax.effects_barrier()
    assert not counter and all(i.loaded for i in infos) and len(infos) == 5
    assert sum(i.n_failed for i in infos) == int((full["status"] != 0).sum())
    assert os.stat(cut / "result.npz").st_mtime_ns == mtime
    assert_bitwise_equal(again, full)


def test_auto_resume_without_manifest(tmp_path, small_auto, monkeypatch):
    """The chunk files alone (the manifest lost) give the chunk size to resume with."""
    grid = make_grid()
    kw = dict(progress=False, mesh=cpu_mesh())

    def stop_after_one(info):
        raise Stop

    with pytest.raises(Stop):
        run_sweep(sweep_fn, grid, out_dir=tmp_path, on_chunk_done=stop_after_one, **kw)
    (tmp_path / "sweep.json").unlink()
    monkeypatch.setattr(_sweep, "_AUTO_CHUNK_BYTES", 8 * OUT_BYTES)
    infos = []
    out = run_sweep(sweep_fn, grid, out_dir=tmp_path, on_chunk_done=infos.append, **kw)
    assert [(i.start, i.stop, i.loaded) for i in infos][:2] == [(0, 24, True),
                                                                 (24, 48, False)]
    ref = run_sweep(sweep_fn, grid, out_dir=tmp_path / "ref", chunk_size=8, **kw)
    assert_bitwise_equal(out, ref)


FEAS = ["--observer", "leso", "--set", "L_d=1e-3", "--set", "L_q=4.9e-3", "--i-q", "2",
        "--zeta1", "0:5:11", "--ratio", "0:2:9", "--speeds", "0.5", "1", "--no-plot"]


def test_feasibility_default_chunks(tmp_path, capsys):
    """`pmsmjax feasibility` without --chunk-size: one chunk (the map is small), no chunk
    file and no result.npz (the command's feasibility.npz holds the map: a finished sweep
    keeps its manifest alone), and the map of the explicit chunks (the same status; the
    angles to rounding: another block width)."""
    assert main(["feasibility", *FEAS, "--out", str(tmp_path / "auto")]) == 0
    assert "sweep: 1 chunk of up to 198 points" in capsys.readouterr().out
    assert sorted(os.listdir(tmp_path / "auto" / "sweep")) == ["sweep.json"]
    manifest = json.loads((tmp_path / "auto" / "sweep" / "sweep.json").read_text())
    assert manifest["complete"] and manifest["result"] is None
    assert main(["feasibility", *FEAS, "--chunk-size", "40", "--out",
                 str(tmp_path / "40")]) == 0
    with np.load(tmp_path / "auto" / "feasibility.npz") as a, \
            np.load(tmp_path / "40" / "feasibility.npz") as b:
        np.testing.assert_array_equal(a["status"], b["status"])
        np.testing.assert_allclose(a["stable_theta_deg"], b["stable_theta_deg"], rtol=1e-13)
    # running it again computes it again (nothing of it was kept), to the same file
    first = dict(np.load(tmp_path / "auto" / "feasibility.npz"))
    assert main(["feasibility", *FEAS, "--out", str(tmp_path / "auto")]) == 0
    assert "reused" not in capsys.readouterr().out
    with np.load(tmp_path / "auto" / "feasibility.npz") as again:
        assert sorted(again.files) == sorted(first)
        for k, v in first.items():  # NaN where a design has no such equilibrium
            np.testing.assert_array_equal(again[k], v)


_TWO_PROCESSES = """
import sys
import jax
jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2,
                           process_id=int(sys.argv[2]))
import numpy as np
from pmsmjax.analysis import _sweep, run_sweep
from tests.test_sweep import make_grid, sweep_fn
from tests.test_sweep_auto import OUT_BYTES

assert jax.device_count() == 4 and jax.local_device_count() == 2
# blocks of 4 devices x 2 points x batch 1; process 0's bound (24 points) is everyone's
_sweep._AUTO_BLOCK_PER_DEVICE = 2
_sweep._AUTO_CHUNK_SECONDS = 1e9
_sweep._AUTO_CHUNK_BYTES = (24 if jax.process_index() == 0 else 8) * OUT_BYTES
infos = []
stop = int(sys.argv[4])

def done(info):
    infos.append(info)
    if info.index == stop:
        raise KeyboardInterrupt

def leave(code):
    # both processes leave together: the coordination service of process 0 aborted once
    # in its gRPC shutdown while process 1 was still leaving (a check in server.cc)
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices("leave")
    jax.distributed.shutdown()
    sys.exit(code)

try:
    out = run_sweep(sweep_fn, make_grid(), out_dir=sys.argv[3], batch_size=1,
                    progress=False, on_chunk_done=done)
except KeyboardInterrupt:
    leave(3)
np.savez(sys.argv[3] + f"_{jax.process_index()}.npz", **out)
print([(i.start, i.stop, i.loaded) for i in infos])
sys.stdout.flush()
leave(0)
"""


def _run_two(tmp_path, out_dir, stop):
    import socket
    import subprocess
    import sys

    from tests.test_sweep import REPO, _subprocess_env

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    procs = [subprocess.Popen(
        [sys.executable, "-c", _TWO_PROCESSES, f"localhost:{port}", str(p), out_dir,
         str(stop)], env=_subprocess_env(2), cwd=REPO, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True) for p in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    return [p.returncode for p in procs], outs


def test_auto_two_processes_interrupted_and_resumed(tmp_path):
    """Two processes with jax.distributed (2 CPU devices each): process 0's automatic
    chunk size is used by both; stopped after the second chunk and run again, every
    process returns the one-process result bit for bit (batch_size=1)."""
    out_dir = str(tmp_path / "two")
    codes, outs = _run_two(tmp_path, out_dir, stop=1)
    assert codes == [3, 3], [o[1][-3000:] for o in outs]
    codes, outs = _run_two(tmp_path, out_dir, stop=-1)
    assert codes == [0, 0], [o[1][-3000:] for o in outs]
    for so, _ in outs:
        assert so.strip().splitlines()[-1] == str(
            [(0, 24, True), (24, 48, True), (48, 72, False), (72, 96, False),
             (96, 105, False)])
    one = run_sweep(sweep_fn, make_grid(), out_dir=tmp_path / "one", chunk_size=8,
                    batch_size=1, progress=False, mesh=cpu_mesh(1))
    for p in range(2):
        with np.load(f"{out_dir}_{p}.npz") as z:
            for k, v in one.items():
                assert z[k].tobytes() == v.tobytes(), (p, k)
    assert sorted(os.listdir(out_dir)) == ["result.npz", "sweep.json"]
