"""The sweep runner: chunking and padding, resume after interruption, several devices and
hosts, and clear errors for bad grids."""

import json
import os
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax
from jax.sharding import Mesh

from pmsmjax.analysis import ChunkInfo, SweepGrid, grid_product, run_sweep


REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
L_Q = 2.7e-3  # q-axis inductance (H)
A_F = 2000.0  # current-filter bandwidth (rad/s)
T = 1e-4  # RK4 step (s)


def sweep_fn(p):
    """dq current dynamics of a PMSM at constant speed plus a first-order current filter.

    Returns the eigenvalues of the 4x4 system matrix and an RK4 step response. For
    |w_m| T > 2.8 explicit RK4 is unstable: those points blow up (status 1), and the
    fastest overflow to inf/NaN. They are the "failing points" of the sweep.
    """
    R_s, L_d, w_m = p["R_s"], p["L_d"], p["w_m"]
    A = jnp.array(
        [
            [-R_s / L_d, w_m * L_Q / L_d, 0.0, 0.0],
            [-w_m * L_d / L_Q, -R_s / L_Q, 0.0, 0.0],
            [A_F, 0.0, -A_F, 0.0],
            [0.0, A_F, 0.0, -A_F],
        ]
    )
    b = jnp.array([0.0, 10.0 / L_Q, 0.0, 0.0])  # u_q = 10 V step

    def f(x):
        return A @ x + b

    def step(x, _):
        k1 = f(x)
        k2 = f(x + 0.5 * T * k1)
        k3 = f(x + 0.5 * T * k2)
        k4 = f(x + T * k3)
        x = x + T / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x, x[1]

    x, i_q = lax.scan(step, jnp.zeros(4), None, length=400)
    ok = jnp.all(jnp.isfinite(x)) & (jnp.max(jnp.abs(x)) < 1e6)
    return {
        "eig": jnp.linalg.eigvals(A),
        "x_end": x,
        "i_q_max": jnp.max(i_q),
        "status": jnp.where(ok, 0, 1).astype(jnp.int32),
    }


def make_grid():
    # 5 * 3 * 7 = 105 points: divisible neither by the chunk sizes used nor by 4 devices.
    return grid_product(
        R_s=np.linspace(0.5, 1.0, 5),
        L_d=np.array([2.0e-3, 2.5e-3, 3.0e-3]),
        w_m=np.linspace(0.0, 4e4, 7),
    )


def assert_bitwise_equal(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def cpu_mesh(n=1):
    return Mesh(np.array(jax.devices("cpu")[:n]), ("points",))


def test_grid_product():
    grid = grid_product(a=[1.0, 2.0], b=np.array([10, 20, 30]))
    assert isinstance(grid, SweepGrid) and isinstance(grid, dict)
    assert grid.shape == (2, 3)
    np.testing.assert_array_equal(grid["a"], [1, 1, 1, 2, 2, 2])
    np.testing.assert_array_equal(grid["b"], [10, 20, 30, 10, 20, 30])
    np.testing.assert_array_equal(grid.axes["b"], [10, 20, 30])
    with pytest.raises(ValueError, match=r"grid_product\(b=...\)` is empty"):
        grid_product(a=[1.0], b=[])
    with pytest.raises(ValueError, match=r"grid_product\(a=...\)` must be a 1-D"):
        grid_product(a=np.ones((2, 2)))
    with pytest.raises(ValueError, match="at least one axis"):
        grid_product()


def test_matches_vmap_and_trims_padding(tmp_path):
    grid = make_grid()
    infos = []
    out = run_sweep(
        sweep_fn, grid, out_dir=tmp_path, chunk_size=16, progress=False, mesh=cpu_mesh(),
        metadata={"model": "dq + filter", "T": T}, on_chunk_done=infos.append,
    )
    # Reference: one vmap over all points, reshaped to the grid.
    ref = jax.jit(jax.vmap(sweep_fn))({k: jnp.asarray(v) for k, v in grid.items()})
    assert out.keys() == ref.keys()
    for k in ref:
        r = np.asarray(ref[k])
        assert out[k].shape == (*grid.shape, *r.shape[1:])
        np.testing.assert_allclose(out[k].reshape(r.shape), r, rtol=1e-12, atol=0)
    # The product grid's points are made on the devices from its axes; the same points
    # sent from the host (a plain dict) give the same outputs bit for bit.
    sent = run_sweep(sweep_fn, dict(grid), out_dir=tmp_path / "sent", chunk_size=16,
                     progress=False, mesh=cpu_mesh(),
                     metadata={"model": "dq + filter", "T": T})
    for k in ref:
        assert sent[k].tobytes() == out[k].tobytes(), k
    # Chunks of 16 points; the last one (105 = 6 * 16 + 9) has 9 real points.
    assert [(i.index, i.start, i.stop) for i in infos] == [
        (i, 16 * i, min(16 * i + 16, 105)) for i in range(7)
    ]
    assert not any(i.loaded for i in infos)
    # The failing points are counted, not fatal.
    x_end = out["x_end"].reshape(105, 4)
    n_nonfinite = int((~np.isfinite(x_end).all(axis=1)).sum())
    n_failed = int((out["status"] != 0).sum())
    assert 0 < n_nonfinite < n_failed < 105
    manifest = json.loads((tmp_path / "sweep.json").read_text())
    assert manifest["complete"] and manifest["n_chunks"] == 7 and manifest["n_points"] == 105
    assert manifest["n_nonfinite"] == n_nonfinite and manifest["n_failed"] == n_failed
    assert sum(i.n_failed for i in infos) == n_failed
    assert manifest["chunks"]["6"]["start"] == 96 and manifest["chunks"]["6"]["stop"] == 105
    assert manifest["metadata"] == {"model": "dq + filter", "T": T}
    assert manifest["grid_shape"] == [5, 3, 7]
    with np.load(tmp_path / "chunk_000006.npz", allow_pickle=False) as z:
        assert z["eig"].shape == (9, 4)
        assert (int(z["__start__"]), int(z["__stop__"])) == (96, 105)
        assert json.loads(str(z["__metadata__"])) == {"model": "dq + filter", "T": T}
        np.testing.assert_array_equal(z["eig"], out["eig"].reshape(105, 4)[96:])
    with np.load(tmp_path / "result.npz", allow_pickle=False) as z:
        for k in out:
            assert z[k].tobytes() == out[k].tobytes()
        np.testing.assert_array_equal(z["grid/w_m"], grid["w_m"].reshape(grid.shape))


def counting(fn, counter):
    """Wrap `fn` so that every evaluated point (padding included) is counted."""

    def wrapped(p):
        jax.debug.callback(lambda _: counter.append(1), p["R_s"])  # once per point
        return fn(p)

    return wrapped


class Interrupt(Exception):
    pass


def test_interrupted_sweep_resumes(tmp_path):
    grid = make_grid()
    kw = dict(chunk_size=16, progress=False, mesh=cpu_mesh())
    counter = []
    fn = counting(sweep_fn, counter)
    full = run_sweep(fn, grid, out_dir=tmp_path / "full", **kw)
    jax.effects_barrier()
    assert len(counter) == 7 * 16  # 7 chunks, all padded to 16 points

    def stop_after_3(info):
        if info.index == 2:
            raise Interrupt

    out_dir = tmp_path / "interrupted"
    with pytest.raises(Interrupt):
        run_sweep(fn, grid, out_dir=out_dir, on_chunk_done=stop_after_3, **kw)
    written = sorted(p.name for p in out_dir.glob("chunk_*.npz"))
    assert written == ["chunk_000000.npz", "chunk_000001.npz", "chunk_000002.npz"]
    assert not (out_dir / "result.npz").exists()
    manifest = json.loads((out_dir / "sweep.json").read_text())
    assert sorted(manifest["chunks"]) == ["0", "1", "2"] and not manifest["complete"]
    stats = {p.name: os.stat(p) for p in out_dir.glob("chunk_*.npz")}
    # A half-written chunk from a killed run: ignored, deleted and computed again.
    (out_dir / ".chunk_000003.npz.1234.deadbeef.tmp").write_bytes(b"PK\x03\x04 garbage")

    counter.clear()
    infos = []
    resumed = run_sweep(fn, grid, out_dir=out_dir, on_chunk_done=infos.append, **kw)
    jax.effects_barrier()
    assert_bitwise_equal(resumed, full)
    assert [i.loaded for i in infos] == [True] * 3 + [False] * 4
    assert len(counter) == 4 * 16  # only the 4 missing chunks were evaluated
    for name, st in stats.items():  # finished chunks were not rewritten
        new = os.stat(out_dir / name)
        assert (new.st_ino, new.st_mtime_ns) == (st.st_ino, st.st_mtime_ns)
    assert not list(out_dir.glob(".*.tmp"))
    with np.load(out_dir / "result.npz") as a, np.load(tmp_path / "full" / "result.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            assert a[k].tobytes() == b[k].tobytes()

    # A complete sweep is only loaded.
    counter.clear()
    again = run_sweep(fn, grid, out_dir=out_dir, **kw)
    jax.effects_barrier()
    assert not counter
    assert_bitwise_equal(again, full)


_FOUR_DEVICES = """
import json, sys
import jax
import numpy as np
from tests.test_sweep import make_grid, sweep_fn
from pmsmjax.analysis import run_sweep

assert jax.device_count() == 4, jax.devices()
report = []
for name, chunk_size, batch_size, padded in [("default", 10, None, 12), ("batched", 16, 4, 16)]:
    infos = []
    run_sweep(sweep_fn, make_grid(), out_dir=sys.argv[1] + "/" + name, chunk_size=chunk_size,
              batch_size=batch_size, progress=False, on_chunk_done=infos.append)
    # Each chunk is padded to `padded` points, padded / 4 on each of the 4 devices.
    for info in infos:
        for s in (info.input_sharding, info.output_sharding):
            assert len(s.device_set) == 4 and not s.is_fully_replicated, s
        assert info.input_sharding.shard_shape((padded,)) == (padded // 4,), info
    report.append([len(infos), infos[-1].start, infos[-1].stop])
print(json.dumps(report))
"""


def _subprocess_env(n_devices):
    env = dict(os.environ)
    # the same XLA flags as this process (pmsmjax.runtime.configure() in conftest), so that
    # both sides compile the same code, plus the device count
    env["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                        f" --xla_force_host_platform_device_count={n_devices}").strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = REPO + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_one_and_four_devices_identical(tmp_path):
    # The device count is fixed when jax starts: run the 4-device sweep in a new process.
    proc = subprocess.run(
        [sys.executable, "-c", _FOUR_DEVICES, str(tmp_path / "four")],
        env=_subprocess_env(4), cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    # 105 points: 11 chunks of 10 (last: 100-104), or 7 chunks of 16 (last: 96-104).
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [[11, 100, 105], [7, 96, 105]]

    for name, chunk_size, batch_size in [("default", 10, None), ("batched", 16, 4)]:
        four_dir = tmp_path / "four" / name
        four_manifest = json.loads((four_dir / "sweep.json").read_text())
        assert four_manifest["devices"]["count"] == 4
        kw = dict(chunk_size=chunk_size, batch_size=batch_size, progress=False, mesh=cpu_mesh(1))
        one = run_sweep(sweep_fn, make_grid(), out_dir=tmp_path / "one" / name, **kw)
        with np.load(four_dir / "result.npz") as four:
            four = dict(four)
        if batch_size is None:
            # Without `batch_size` the vmap width differs (10 vs 3), and XLA's CPU code may
            # then differ where NaN meets a reduction (see `run_sweep`'s docstring): compare
            # the points that did not blow up.
            np.testing.assert_array_equal(four["status"], one["status"])
            ok = one["status"] == 0
            assert 0 < ok.sum() < ok.size
            four = {k: four[k][ok] for k in one}
            one_cmp = {k: v[ok] for k, v in one.items()}
        else:  # bitwise identical everywhere, NaNs included
            one_cmp = one
        for k, v in one_cmp.items():
            assert four[k].tobytes() == v.tobytes(), (name, k)
        # Same sweep whatever the device count: a 1-device run resumes the 4-device one.
        one_manifest = json.loads((tmp_path / "one" / name / "sweep.json").read_text())
        assert one_manifest["fingerprint"] == four_manifest["fingerprint"]
        infos = []
        resumed = run_sweep(sweep_fn, make_grid(), out_dir=four_dir, on_chunk_done=infos.append,
                            **kw)
        assert all(i.loaded for i in infos)
        assert_bitwise_equal(resumed, one)


_TWO_HOSTS = """
import sys
import jax
jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2,
                           process_id=int(sys.argv[2]))
import numpy as np
from tests.test_sweep import make_grid, sweep_fn
from pmsmjax.analysis import run_sweep

assert jax.device_count() == 4 and jax.local_device_count() == 2
out = run_sweep(sweep_fn, make_grid(), out_dir=sys.argv[3], chunk_size=16, batch_size=4,
                progress=False)
np.savez(sys.argv[3] + f"_{jax.process_index()}.npz", **out)
"""


def test_two_processes_with_jax_distributed(tmp_path):
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    out_dir = str(tmp_path / "two")
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _TWO_HOSTS, f"localhost:{port}", str(p), out_dir],
            env=_subprocess_env(2), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )
        for p in range(2)
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-3000:]
    one = run_sweep(
        sweep_fn, make_grid(), out_dir=tmp_path / "one", chunk_size=16, batch_size=4,
        progress=False, mesh=cpu_mesh(1),
    )
    for p in range(2):  # every process returns the full result
        with np.load(f"{out_dir}_{p}.npz") as z:
            for k, v in one.items():
                assert z[k].tobytes() == v.tobytes(), (p, k)
    assert len(list((tmp_path / "two").glob("chunk_*.npz"))) == 7


def simple_fn(p):
    return {"y": jnp.sin(p["a"]) * p["b"]}


@pytest.mark.parametrize(
    "grid, match",
    [
        ({}, r"grid=...\)` is empty"),
        ({"a": np.array([]), "b": np.array([])}, r"grid\['a'\]` is empty"),
        ({"a": np.ones(3), "b": np.ones(4)}, r"same length.*'a': 3, 'b': 4"),
        ({"a": np.ones(3), "b": np.array([1.0, np.nan, 2.0])}, r"grid\['b'\]`.*index 1"),
        ({"a": np.array([1.0, -np.inf]), "b": np.ones(2)}, r"grid\['a'\]`.*non-finite"),
        ({"a": np.ones((2, 2)), "b": np.ones(2)}, r"grid\['a'\]` must be a 1-D.*\(2, 2\)"),
        ({"a": 1.0, "b": np.ones(2)}, r"grid\['a'\]` must be a 1-D.*\(\)"),
        ({"a": np.array(["x", "y"]), "b": np.ones(2)}, r"grid\['a'\]` must hold numbers"),
        ({"a": [1.0, [2.0, 3.0]], "b": np.ones(2)}, r"grid\['a'\]`"),
        ({1: np.ones(2)}, "keys must be strings"),
    ],
)
def test_bad_grids(tmp_path, grid, match):
    with pytest.raises(ValueError, match=match):
        run_sweep(simple_fn, grid, out_dir=tmp_path, chunk_size=4, progress=False)
    assert not (tmp_path / "sweep.json").exists()


def test_bad_arguments(tmp_path):
    grid = {"a": np.linspace(0, 1, 5), "b": np.ones(5)}
    kw = dict(out_dir=tmp_path, progress=False)
    with pytest.raises(TypeError, match="dict of 1-D arrays"):
        run_sweep(simple_fn, [np.ones(3)], chunk_size=2, **kw)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="chunk_size"):
            run_sweep(simple_fn, grid, chunk_size=bad, **kw)
        with pytest.raises(ValueError, match="batch_size"):
            run_sweep(simple_fn, grid, chunk_size=2, batch_size=bad, **kw)
    with pytest.raises(ValueError, match="metadata.*JSON"):
        run_sweep(simple_fn, grid, chunk_size=2, metadata={"f": simple_fn}, **kw)
    with pytest.raises(ValueError, match="metadata.*JSON"):
        run_sweep(simple_fn, grid, chunk_size=2, metadata={"x": float("nan")}, **kw)
    # Non-finite values are fine when asked for, and reach `fn`.
    grid["b"][2] = np.nan
    out = run_sweep(simple_fn, grid, chunk_size=2, allow_nonfinite=True, **kw)
    assert np.isnan(out["y"][2]) and np.isfinite(out["y"][[0, 1, 3, 4]]).all()


def test_a_product_grid_is_identified_by_its_axes(tmp_path):
    """A grid from `grid_product` is hashed by its axes (16 kB instead of every point);
    its arrays are read-only, and a grid whose arrays were replaced or extended is hashed
    by its points: another product, or another grid, is still another sweep."""
    from pmsmjax.analysis._sweep_spec import _hash_grid

    grid = grid_product(a=np.linspace(0, 1, 5), b=np.array([1.0, 2.0]))
    for a in (*grid.values(), *grid.axes.values()):
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 7.0
    assert grid.product_axes() is grid.axes
    h = _hash_grid(dict(grid), grid.shape, grid.product_axes())
    same = grid_product(a=np.linspace(0, 1, 5), b=np.array([1.0, 2.0]))
    assert _hash_grid(dict(same), same.shape, same.product_axes()) == h
    other = grid_product(a=np.linspace(0, 1, 5), b=np.array([1.0, 2.5]))
    assert _hash_grid(dict(other), other.shape, other.product_axes()) != h
    changed = SweepGrid(dict(grid), shape=grid.shape, axes=grid.axes)
    assert changed.product_axes() is None  # not made by grid_product
    replaced = grid_product(a=np.linspace(0, 1, 5), b=np.array([1.0, 2.0]))
    replaced["b"] = replaced["b"] * 2.0
    extended = grid_product(a=np.linspace(0, 1, 5), b=np.array([1.0, 2.0]))
    extended["index"] = np.arange(10)
    assert replaced.product_axes() is None and extended.product_axes() is None
    # a sweep begun on the product resumes on the same product, and refuses another
    kw = dict(out_dir=tmp_path, progress=False, chunk_size=4)
    first = run_sweep(simple_fn, grid, **kw)
    again = run_sweep(simple_fn, same, **kw)
    np.testing.assert_array_equal(again["y"], first["y"])
    with pytest.raises(ValueError, match=r"differs in: grid\)"):
        run_sweep(simple_fn, replaced, **kw)
    # a float32 sweep hashes the axes as converted: another sweep
    with pytest.raises(ValueError, match=r"differs in: grid"):
        run_sweep(simple_fn, grid, dtype=np.float32, **kw)


def test_mismatched_resume_raises(tmp_path):
    grid = {"a": np.linspace(0, 1, 10), "b": np.ones(10)}
    kw = dict(out_dir=tmp_path, progress=False)
    first = run_sweep(simple_fn, grid, chunk_size=4, metadata={"run": 1}, **kw)
    other = {"a": np.linspace(0, 2, 10), "b": np.ones(10)}
    with pytest.raises(ValueError, match=r"different sweep.*grid.*another `out_dir`.*resume=False"):
        run_sweep(simple_fn, other, chunk_size=4, metadata={"run": 1}, **kw)
    with pytest.raises(ValueError, match=r"differs in: chunk_size\)"):
        run_sweep(simple_fn, grid, chunk_size=5, metadata={"run": 1}, **kw)
    with pytest.raises(ValueError, match=r"differs in: metadata\)"):
        run_sweep(simple_fn, grid, chunk_size=4, metadata={"run": 2}, **kw)
    with pytest.raises(ValueError, match=r"differs in: fn\)"):
        run_sweep(lambda p: {"y": jnp.cos(p["a"]) * p["b"]}, grid, chunk_size=4,
                  metadata={"run": 1}, **kw)
    with pytest.raises(ValueError, match=r"differs in: grid, outputs, fn\)"):  # float32
        run_sweep(simple_fn, grid, chunk_size=4, metadata={"run": 1}, dtype=np.float32, **kw)
    # Nothing was touched by the refused runs.
    assert json.loads((tmp_path / "sweep.json").read_text())["metadata"] == {"run": 1}
    # resume=False starts over.
    second = run_sweep(simple_fn, other, chunk_size=4, metadata={"run": 1}, resume=False, **kw)
    np.testing.assert_array_equal(second["y"], first["y"] * 0 + np.sin(other["a"]))
    # A stray chunk of another sweep is refused even without a manifest.
    (tmp_path / "sweep.json").unlink()
    with pytest.raises(ValueError, match="chunk file chunk_000000.npz"):
        run_sweep(simple_fn, grid, chunk_size=4, metadata={"run": 1}, **kw)


def test_raising_fn_keeps_finished_chunks(tmp_path):
    import equinox as eqx

    def fn(p):
        return {"y": eqx.error_if(p["a"], p["a"] > 6.5, "a too large")}

    grid = {"a": np.arange(10.0)}
    with pytest.raises(RuntimeError, match=r"failed on chunk 3 \(points 6 to 7\).*resume"):
        run_sweep(fn, grid, out_dir=tmp_path, chunk_size=2, progress=False)
    assert len(list(tmp_path.glob("chunk_*.npz"))) == 3
    manifest = json.loads((tmp_path / "sweep.json").read_text())
    assert manifest["chunks"]["3"]["status"] == "error"


def test_outputs_pytree_float32_and_progress(tmp_path, capsys):
    def fn(p):
        return (jnp.stack([p["x"], p["x"] ** 2]), {"n": p["k"] * 2})

    grid = {"x": np.linspace(0, 1, 7), "k": np.arange(7)}
    out = run_sweep(fn, grid, out_dir=tmp_path, chunk_size=3, dtype=np.float32)
    assert out[0].dtype == np.float32 and out[0].shape == (7, 2)
    np.testing.assert_array_equal(out[1]["n"], 2 * np.arange(7))
    assert "pt/s" in capsys.readouterr().err
    with np.load(tmp_path / "result.npz") as z:
        assert {"0", "1/n", "grid/x", "grid/k"} <= set(z.files)
    assert ChunkInfo.__dataclass_fields__.keys() >= {"index", "loaded", "n_nonfinite"}
