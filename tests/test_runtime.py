"""The entry points' process settings (`pmsmjax.runtime`): XLA flags, the persistent
compilation cache (filled by a command, reused, cleared, opted out of)."""

import json
import math
import os
import subprocess
import sys
import warnings

import pytest

import pmsmjax as pj


def _run(args, env):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          env=env, timeout=600)


@pytest.fixture
def env(tmp_path):
    e = dict(os.environ)
    e["PMSMJAX_CACHE_DIR"] = str(tmp_path / "cache")
    e.pop("PMSMJAX_CACHE", None)
    e.pop("XLA_FLAGS", None)
    return e


def test_configure_in_a_fresh_process(env, tmp_path, monkeypatch):
    """The settings `configure()` applies in a fresh process, and the cache opted out of
    (`PMSMJAX_CACHE=0`): JAX's own counters of the persistent cache (as in `_COUNTING`) see the
    process's one compiled program written to the cache with it on, and no use of the
    cache with it off, nor a cache folder made."""
    code = ("import pmsmjax as pj, jax, jax.monitoring, os, json, collections\n"
            "n = collections.Counter()\n"
            "jax.monitoring.register_event_listener(lambda e, **kw: n.update([e]))\n"
            "import gc\n"
            "gc_default = gc.get_threshold()\n"
            "r = pj.runtime.configure()\n"
            "jax.numpy.ones(3).block_until_ready()\n"
            "print(json.dumps(dict(r, flags=os.environ['XLA_FLAGS'],"
            " cache=jax.config.jax_compilation_cache_dir,"
            " async_dispatch=jax.config.read('jax_cpu_enable_async_dispatch'),"
            " store=pj.runtime._stored._STORE_DIR and str(pj.runtime._stored._STORE_DIR),"
            " gc_default=gc_default, gc_now=gc.get_threshold(),"
            " hits=n['/jax/compilation_cache/cache_hits'],"
            " misses=n['/jax/compilation_cache/cache_misses'])))\n")
    res = _run(["-c", code], env)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert "xla_cpu_small_while_loop_byte_threshold" in out["flags"]
    # the hang settings (BENCHMARKS.md, "Hangs"): Eigen single-threaded; asynchronous CPU
    # dispatch stays on (the library's programs have no host callback inside a loop)
    assert "--xla_cpu_multi_thread_eigen=false" in out["flags"].split()
    assert out["async_dispatch"] is True
    assert out["cache"] == str(tmp_path / "cache") == out["cache_dir"]
    assert out["backend_was_started"] is False
    # fewer garbage collections: the collector's thresholds, set and reported
    assert out["gc_now"] == out["gc_thresholds"] == list(pj.runtime.GC_THRESHOLDS)
    assert out["gc_default"] != out["gc_now"]
    assert out["hits"] == 0 and out["misses"] >= 1  # compiled and written to the cache
    assert out["store"].startswith(str(tmp_path / "cache"))  # stored programs there too
    assert any(p.is_file() for p in (tmp_path / "cache").rglob("*"))
    env["PMSMJAX_CACHE"] = "0"
    env["PMSMJAX_FAST_LOOPS"] = "0"
    env["PMSMJAX_GC"] = "0"
    env["PMSMJAX_CACHE_DIR"] = str(tmp_path / "off")
    res = _run(["-c", code.replace("os.environ['XLA_FLAGS']",
                                   "os.environ.get('XLA_FLAGS', '')")], env)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["cache"] is None and out["cache_dir"] is None
    assert out["hits"] == out["misses"] == 0  # the cache is not used
    assert out["store"] is None  # nor the stored programs (stored_call is off)
    assert not (tmp_path / "off").exists()
    assert "small_while_loop" not in out["flags"]
    assert out["gc_now"] == out["gc_thresholds"] == out["gc_default"]  # Python's own
    # a bad value is an error naming it, raised first, before configure() changes
    # anything (so in this process, which has long been configured)
    monkeypatch.setenv("PMSMJAX_CACHE", "maybe")
    with pytest.raises(ValueError, match="PMSMJAX_CACHE='maybe'"):
        pj.runtime.configure()


def test_configure_after_the_backend_started_warns(monkeypatch):
    import jax

    jax.numpy.zeros(1).block_until_ready()  # the backend is running in this process
    monkeypatch.setenv("XLA_FLAGS", "")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        r = pj.runtime.configure(cache=False, fast_loops=True)
    assert r["backend_was_started"]
    assert any("after JAX started its backend" in str(x.message) for x in w)
    assert os.environ["XLA_FLAGS"] == ""  # not pretended to be applied


# `python -m pmsmjax ARGS` with JAX's own counters of the persistent cache (jax.monitoring
# events, recorded by JAX's compiler whenever it looks a program up in the cache) printed
# on stderr at exit: hits (a compiled program read from the cache) and misses (compiled
# and written to it).
_COUNTING = (
    "import atexit, collections, runpy, sys\n"
    "import jax.monitoring\n"
    "n = collections.Counter()\n"
    "jax.monitoring.register_event_listener(lambda e, **kw: n.update([e]))\n"
    "atexit.register(lambda: print('CACHE', n['/jax/compilation_cache/cache_hits'],"
    " n['/jax/compilation_cache/cache_misses'], file=sys.stderr))\n"
    "sys.argv = ['pmsmjax', *sys.argv[1:]]\n"
    "runpy.run_module('pmsmjax', run_name='__main__')\n")


def _hits_misses(res):
    line = [ln for ln in res.stderr.splitlines() if ln.startswith("CACHE ")][-1]
    return tuple(int(v) for v in line.split()[1:])


def _cache_files(d):
    return {str(p): p.stat().st_mtime_ns for p in d.rglob("*") if p.is_file()}


def test_cache_is_filled_reused_and_cleared(env, tmp_path):
    """A second process reuses the first one's compiled programs: JAX reports a cache hit
    for every program the first one wrote and compiles (misses) nothing, and the cache's
    files are the same files, untouched."""
    args = ["equilibria", "--speed", "0.5", "--json"]
    cmd = ["-c", _COUNTING, *args]
    first = _run(cmd, env)
    assert first.returncode == 0, first.stderr
    assert "after JAX started its backend" not in first.stderr  # configured in time
    files = [p for p in (tmp_path / "cache").rglob("*") if p.is_file()]
    n, size = len(files), sum(p.stat().st_size for p in files)
    assert n > 0 and size > 0
    assert not [p for p in files if p.name.endswith(".tmp")]  # every entry renamed in place
    hits1, misses1 = _hits_misses(first)
    assert hits1 == 0 and misses1 > 0  # an empty cache: everything compiled and written
    before = _cache_files(tmp_path / "cache")
    second = _run(cmd, env)
    assert second.returncode == 0 and second.stdout == first.stdout  # same result, cached
    hits2, misses2 = _hits_misses(second)
    # every program written by the first process is read back, none compiled again
    assert misses2 == 0 and hits2 >= misses1, (hits1, misses1, hits2, misses2)
    assert _cache_files(tmp_path / "cache") == before  # nothing written or rewritten
    # `pmsmjax cache`, then `pmsmjax cache --clear`: the command line's own entry point,
    # both in one process (neither compiles anything; a process each only imports JAX
    # twice)
    both = _run(["-c", "import sys\nfrom pmsmjax.cli.__main__ import main\n"
                       "sys.exit(main(['cache']) or main(['cache', '--clear']))"], env)
    assert both.returncode == 0, both.stderr
    info, cleared = both.stdout.split("removed ")
    assert f"({n} files" in info and str(tmp_path / "cache") in info
    assert cleared.startswith(f"{n} files")
    assert not (tmp_path / "cache").exists()
    # opting out (PMSMJAX_CACHE=0, read by configure() as this command calls it):
    # test_configure_in_a_fresh_process, with JAX's counters


def test_cache_entries_are_written_whole(tmp_path, monkeypatch):
    """Processes sharing the compilation cache never read an entry another is still
    writing (JAX writes in place; once, a cold test run failed on the warning): after
    `configure`, an entry appears only whole (a reader polling while a large entry is
    written sees nothing or all of it), a write interrupted before its rename leaves no
    entry and no temporary file, and the first entry stays (JAX's rule)."""
    import threading

    from jax._src.lru_cache import LRUCache

    assert pj.runtime.configure()["cache_dir"]  # (the suite runs with the cache on)
    assert hasattr(LRUCache.put, "_pmsmjax_original")
    cache = LRUCache(str(tmp_path), max_size=-1)
    big = bytes(range(256)) * (1 << 17)  # 32 MiB: a write long enough to be seen
    for i in range(3):
        key, seen = f"big{i}", []
        done = threading.Event()

        def read(key=key, seen=seen, done=done):
            while not done.is_set():
                v = cache.get(key)
                if v is not None:
                    seen.append(len(v))

        t = threading.Thread(target=read)
        t.start()
        cache.put(key, big)
        done.set()
        t.join()
        assert set(seen) <= {len(big)}, sorted(set(seen))[:5]
        assert cache.get(key) == big
    cache.put("big0", b"other")
    assert cache.get("big0") == big

    from pmsmjax import _files

    def killed(*a):
        raise KeyboardInterrupt

    monkeypatch.setattr(_files.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        cache.put("cut", b"x" * 1000)
    monkeypatch.undo()
    assert cache.get("cut") is None
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"big{i}-cache" for i in range(3)]


# ---------------------------------------------------------------------------------------
# Memory mappings: compiled programs hold them; at vm.max_map_count compilation kills
# the process (the test suite's native worker crashes); release_compiled prevents it
# ---------------------------------------------------------------------------------------

linux_only = pytest.mark.skipif(pj.runtime.memory_maps() is None,
                                reason="memory mappings are counted from /proc (Linux)")


_RELEASE = """
import json, math
import jax, jax.numpy as jnp
import pmsmjax as pj
n0, limit = pj.runtime.memory_maps()
keep = []
for k in range(40):
    f = jax.jit(lambda x, k=k: jnp.cos(x * k) + jnp.cumsum(x) * k)
    f(jnp.ones(5)).block_until_ready()
    keep.append(f)
n1, _ = pj.runtime.memory_maps()
below = pj.runtime.release_compiled(1.0)
released = pj.runtime.release_compiled(0.0)
n2, _ = pj.runtime.memory_maps()
again = float(keep[3](jnp.ones(5))[0])
print(json.dumps(dict(n0=n0, n1=n1, n2=n2, limit=limit, below=below, released=released,
                      again=again)))
"""


@linux_only
def test_release_compiled_drops_the_mappings_of_compiled_programs(env):
    """In a process of its own: a release drops every compiled program of the process
    (`jax.clear_caches()`), which in a test worker would cost its later tests their
    programs."""
    res = _run(["-c", _RELEASE], env)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert 0 < out["n0"] < out["limit"]
    assert out["n1"] - out["n0"] >= 80          # a few mappings per kept program
    assert not out["below"]                      # far below the limit: nothing dropped
    assert out["released"]
    assert out["n1"] - out["n2"] >= 0.6 * (out["n1"] - out["n0"])  # (the rest: buffers
    # and JAX internals)
    assert out["again"] == pytest.approx(math.cos(3.0) + 3.0)  # compiled again
    with pytest.raises(ValueError, match="fraction"):
        pj.runtime.release_compiled(1.5)


@linux_only
@pytest.mark.skipif((pj.runtime.memory_maps() or (0, 0))[1] > 300_000,
                    reason="vm.max_map_count too large to fill in a test")
def test_the_mapping_limit_kills_compilation_and_release_compiled_prevents_it():
    """benchmarks/reproducers/map_limit.py: a process with all but 60 of its allowed
    mappings taken dies within a few compilations (a segfault after LLVM's "Cannot
    allocate memory" when run alone; an abort in one full-suite run); releasing compiled
    programs after each one keeps it alive through 12."""
    from benchmarks.reproducers import map_limit
    dies = map_limit.run(headroom=60, programs=12, release=False, timeout=280)
    assert dies["fatal_signal"] and dies["out_of_memory"] and not dies["finished"], dies
    assert dies["compiled"] < 12
    lives = map_limit.run(headroom=60, programs=12, release=True, timeout=280)
    assert lives["finished"] and lives["returncode"] == 0 and lives["compiled"] == 12, lives


def test_a_plain_import_gets_the_fast_settings(env):
    """`import pmsmjax` alone puts the XLA flags in place before JAX starts its backend
    (a plain script's single runs are fast without `configure()`); imported after JAX
    computed something it warns once and says how."""
    code = ("import os, jax, pmsmjax\n"
            "jax.numpy.ones(3).block_until_ready()\n"
            "print(os.environ.get('XLA_FLAGS', ''))\n")
    res = _run(["-c", code], env)
    assert res.returncode == 0, res.stderr
    flags = res.stdout.strip().splitlines()[-1].split()
    assert "--xla_cpu_multi_thread_eigen=false" in flags
    assert any("xla_cpu_small_while_loop_byte_threshold=65536" in f for f in flags)
    assert "RuntimeWarning" not in res.stderr
    late = ("import jax\njax.numpy.ones(3).block_until_ready()\n"
            "import pmsmjax\nimport importlib\n"
            "pmsmjax.runtime.apply_xla_flags()\n")  # a second call: no second warning
    res = _run(["-c", late], env)
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("JAX started its backend before pmsmjax set its XLA flags") == 1
    assert "XLA_FLAGS='" in res.stderr


_BOTH_SETTINGS = """
import json, os, sys
import numpy as np
import jax, pmsmjax as pj
from pmsmjax.analysis import equilibria
from pmsmjax.observers import make_observer
d = pj.preset("zhang750")
obs = make_observer("leso", d, motor=pj.replace_params(d, L_q=1.2 * d.motor.L_q).motor)
sc = pj.Scenario(t_end=0.05, w_m_ref=pj.Profile.constant(0.5 * float(d.w_rated)),
                 tau_L=pj.Profile.constant(1.0))
r = pj.simulate(d, pj.FOC.from_drive(d), make_observer("eso", d), sc, w_m0=10.0)
eq = jax.device_get(equilibria(obs, d.motor, 0.5 * float(d.w_rated),
                               np.array([0.0, 0.3 * float(d.base.I_b)])))
v = np.asarray(eq.valid)
with open(sys.argv[1], "w") as f:
    json.dump(dict(flags=os.environ.get("XLA_FLAGS", ""),
                   tb_limit=jax.config.jax_traceback_in_locations_limit,
                   theta_err=np.asarray(r.theta_err).tolist(),
                   w_hat=np.asarray(r.w_hat).tolist(), theta=np.asarray(eq.theta)[v].tolist(),
                   stable=np.asarray(eq.stable)[v].tolist(), status=int(eq.status)), f)
"""


def test_quick_compiles_give_the_same_numbers(env, tmp_path, monkeypatch):
    """The test suite compiles at LLVM's lowest optimisation level with XLA's older
    kernel emitters (`PMSMJAX_QUICK_COMPILE=1`, conftest.py); a user's process does not.
    The same closed-loop run (an ESO, 50 ms at half speed with a load step) and the same
    equilibrium analysis (a mismatched LESO) under each setting: the default in a fresh
    process, the quick one in this process, the suite's own (in a fresh process too
    where the suite runs without it): the same numbers up to round-off, so what the suite
    checks holds for the default build."""
    out = {}
    quick_here = set(pj.runtime._settings.QUICK_COMPILE_FLAGS) <= set(
        os.environ.get("XLA_FLAGS", "").split())
    for quick in ("0", "1"):
        path = str(tmp_path / f"{quick}.json")
        if quick == "1" and quick_here:
            # the script as run with `python -c` (the same programs this process has
            # compiled, or reads from its cache, under the same flags)
            monkeypatch.setattr(sys, "argv", ["-c", path])
            exec(compile(_BOTH_SETTINGS, "<_BOTH_SETTINGS>", "exec"), {"__name__": "x"})
        else:
            e = dict(env, PMSMJAX_QUICK_COMPILE=quick, PMSMJAX_CACHE="0")
            res = _run(["-c", _BOTH_SETTINGS, path], e)
            assert res.returncode == 0, res.stderr
        out[quick] = json.loads((tmp_path / f"{quick}.json").read_text())
    assert "--xla_backend_optimization_level=0" in out["1"]["flags"].split()
    assert "--xla_cpu_use_fusion_emitters=false" in out["1"]["flags"].split()
    assert "--xla_cpu_parallel_codegen_split_count=1" in out["1"]["flags"].split()
    assert "xla_backend_optimization_level" not in out["0"]["flags"]
    # no Python tracebacks in the source locations under quick compiles only
    assert out["1"]["tb_limit"] == 0 and out["0"]["tb_limit"] > 0
    a, b = out["0"], out["1"]
    # They differ in round-off only (measured: 7e-15 rad, 2e-13 rad/s of 505 rad/s, 1e-15
    # rad); 1000x margin, as the order of floating-point operations differs by machine.
    np.testing.assert_allclose(b["theta_err"], a["theta_err"], rtol=0, atol=1e-11)
    np.testing.assert_allclose(b["w_hat"], a["w_hat"], rtol=1e-12, atol=1e-10)
    assert b["status"] == a["status"] == 0 and b["stable"] == a["stable"]
    assert len(a["theta"]) >= 2  # the designed one and at least one other equilibrium
    np.testing.assert_allclose(b["theta"], a["theta"], rtol=0, atol=1e-12)


def test_quick_compiles_leave_a_users_jax_traceback_setting(monkeypatch):
    """Quick compiles set `QUICK_COMPILE_JAX_CONFIG`, except where the user set the same
    option through JAX's environment variable."""
    import jax

    from pmsmjax.runtime import _settings as S

    before = jax.config.jax_traceback_in_locations_limit
    try:
        monkeypatch.setenv("PMSMJAX_QUICK_COMPILE", "1")
        monkeypatch.delenv("JAX_TRACEBACK_IN_LOCATIONS_LIMIT", raising=False)
        jax.config.update("jax_traceback_in_locations_limit", 7)
        S._apply_quick_jax_config()
        assert jax.config.jax_traceback_in_locations_limit == 0
        jax.config.update("jax_traceback_in_locations_limit", 7)
        monkeypatch.setenv("JAX_TRACEBACK_IN_LOCATIONS_LIMIT", "7")
        S._apply_quick_jax_config()
        assert jax.config.jax_traceback_in_locations_limit == 7
        monkeypatch.setenv("PMSMJAX_QUICK_COMPILE", "0")
        monkeypatch.delenv("JAX_TRACEBACK_IN_LOCATIONS_LIMIT")
        S._apply_quick_jax_config()
        assert jax.config.jax_traceback_in_locations_limit == 7
    finally:
        jax.config.update("jax_traceback_in_locations_limit", before)


def test_long_run_options_undo_quick_compiles_for_one_program(monkeypatch):
    """`long_run_compiler_options` are XLA's names (an unknown one fails the compile) and
    its values, only under quick compiles; the program gives the same numbers."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    monkeypatch.setenv("PMSMJAX_QUICK_COMPILE", "0")
    assert pj.runtime.long_run_compiler_options() is None
    monkeypatch.setenv("PMSMJAX_QUICK_COMPILE", "1")
    opts = pj.runtime.long_run_compiler_options()
    assert opts == {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True}

    def f(x):
        return jnp.exp(-x) * jnp.sin(3.0 * x) + jnp.cumsum(x ** 2)

    x = jnp.linspace(0.0, 2.0, 257)
    want = np.exp(-np.asarray(x)) * np.sin(3.0 * np.asarray(x)) + np.cumsum(np.asarray(x) ** 2)
    np.testing.assert_allclose(np.asarray(jax.jit(f, compiler_options=opts)(x)), want,
                               rtol=1e-13)
    with pytest.raises(Exception, match="compile option"):
        jax.jit(f, compiler_options={"xla_no_such_option": 3})(x)


def test_new_initial_values_do_not_compile_again():
    """Python numbers as initial values (angle, speed, estimate, current) run the
    program already compiled."""
    from pmsmjax._sim import _simulate as S

    d = pj.preset("zhang750")
    foc = pj.FOC.from_drive(d)
    obs = pj.observers.make_observer("eso", d)
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(300.0))
    runs = []
    for th in (0.0, 0.3, -1.2):
        pj.simulate(d, foc, obs, sc, theta0=th, w_m0=100.0 + th, theta_hat0=th + 0.1,
                    w_hat0=90.0, i_dq0=(0.0, th))
        runs.append(S._simulate._cached._cache_size())
    assert runs[1] == runs[2] == runs[0]
    # and the values are used: a different initial angle gives a different run
    a = pj.simulate(d, foc, obs, sc, theta0=0.0)
    b = pj.simulate(d, foc, obs, sc, theta0=0.4)
    assert float(b.theta[0]) == pytest.approx(0.4) and float(a.theta[0]) == 0.0


def test_new_parameter_values_do_not_compile_again(monkeypatch):
    """Python floats in the drive, the controller's and the observer's machine model,
    the observer's design (a preset, `replace_params`, `scale_motor`, `make_observer(...,
    zeta1=...)`) and the measurement chain (`Sensing(noise_std=...)`) are traced values:
    `simulate`, `replay`, `harmonic_ripple` and the certificate run their compiled
    program again for new values (one entry in each jit cache), use the values, and give
    the numbers of the program that baked them in (the conversion patched out) to
    rounding."""
    import jax

    from pmsmjax._data import _replay
    from pmsmjax._sim import _simulate as S
    from pmsmjax.analysis import _harmonic, _lyapunov

    d = pj.preset("zhang750")
    foc = pj.FOC.from_drive(d)
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(300.0))
    mk = pj.observers.make_observer

    def run(zeta1, k_psi, k_Lq):
        drive = pj.replace_params(d, L_q=float(d.motor.L_q) * k_Lq)
        obs = mk("leso", d, zeta1=zeta1, ratio=1.0).with_motor(
            pj.scale_motor(d.motor, {"psi_f": k_psi}))
        return pj.simulate(drive, foc, obs, sc, theta0=0.2, theta_hat0=0.0, w_m0=200.0)

    cases = [(0.7, 1.0, 1.0), (1.3, 0.9, 1.0), (1.3, 1.0, 1.4)]
    size = lambda jitted: jitted._cached._cache_size()  # noqa: E731
    trs = [run(*cases[0])]
    n_sim = size(S._simulate)
    for c in cases[1:]:
        trs.append(run(*c))
        assert size(S._simulate) == n_sim
    errs = [np.asarray(t.theta_err) for t in trs]
    assert min(np.max(np.abs(errs[0] - e)) for e in errs[1:]) > 1e-4  # the values act

    def noisy(std):  # another current-noise level: the same program
        return pj.simulate(d, foc, mk("leso", d, zeta1=0.7, ratio=1.0), sc, theta0=0.2,
                           theta_hat0=0.0, w_m0=200.0, sensing=pj.Sensing(noise_std=std),
                           key=jax.random.PRNGKey(0))

    noisy_errs = [np.asarray(noisy(0.02).theta_err)]
    n_noisy = size(S._simulate)
    noisy_errs.append(np.asarray(noisy(0.05).theta_err))
    assert size(S._simulate) == n_noisy
    # the same draws scaled: the angle errors differ (by the noise through the observer)
    assert np.max(np.abs(noisy_errs[0] - noisy_errs[1])) > 1e-6

    u, i = np.asarray(trs[0].u_ab), np.asarray(trs[0].i_meas_ab)

    def rep(zeta1):
        return pj.replay(mk("leso", d, zeta1=zeta1, ratio=1.0), u_ab=u, i_ab=i, T_s=125e-6,
                         theta0=0.0, w0=200.0)[0]

    reps = [np.asarray(rep(0.7))]
    n_rep = size(_replay._scan)
    reps.append(np.asarray(rep(1.3)))
    assert size(_replay._scan) == n_rep
    assert np.max(np.abs(reps[0] - reps[1])) > 1e-6

    op = pj.analysis.OperatingPoint(0.5 * float(d.w_rated), (0.0, 1.0))
    rip = [pj.analysis.harmonic_ripple(mk("eso", d, w2=200.0), d, op, (-5, 7))]
    n_rip = size(_harmonic._harmonic_ripple)
    rip.append(pj.analysis.harmonic_ripple(mk("eso", d, w2=400.0), d, op, (-5, 7)))
    assert size(_harmonic._harmonic_ripple) == n_rip
    assert not np.allclose(np.asarray(rip[0]), np.asarray(rip[1]))

    small = dict(n_speed=5, n_time=20, n_dirs=16, n_refine=3, n_k1_speeds=2,
                 alphas=(0.5, 0.9), radii=np.geomspace(1e-6, 1.0, 8))
    def cert(zeta1):
        return pj.analysis.slowly_varying_certificate(
            d, mk("leso", d, zeta1=zeta1, ratio=1.0, w2=300.0), (0.2, 1.0), **small)

    certs = [cert(0.8)]
    n_cert = size(_lyapunov._certificate)
    certs.append(cert(1.5))
    assert size(_lyapunov._certificate) == n_cert
    assert float(certs[0].sigma) != float(certs[1].sigma)

    # the same numbers as the programs with the values baked in (conversion patched out)
    for mod in (S, _replay, _harmonic, _lyapunov):
        monkeypatch.setattr(mod, "values_as_arrays", lambda tree, dtype: tree)
    np.testing.assert_allclose(np.asarray(run(*cases[2]).theta_err), errs[2], rtol=0,
                               atol=1e-9)
    assert size(S._simulate) == n_noisy + 1  # a new program: the values baked in
    np.testing.assert_allclose(np.asarray(noisy(0.05).theta_err), noisy_errs[1], rtol=0,
                               atol=1e-9)
    assert size(S._simulate) == n_noisy + 2
    np.testing.assert_allclose(np.asarray(rep(1.3)), reps[1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(pj.analysis.harmonic_ripple(mk("eso", d, w2=400.0), d, op, (-5, 7))),
        np.asarray(rip[1]), rtol=1e-9)
    # a bad value set by with_design (which skips the construction checks) still raises
    # before the run traces it, naming the parameter
    with pytest.raises(ValueError, match=r"ESOObserver\(a=\.\.\.\).*got 1\.5"):
        pj.simulate(d, foc, mk("eso", d).with_design(a=1.5), sc)
    with pytest.raises(ValueError, match=r"ESOObserver\(a=\.\.\.\).*got 1\.5"):
        pj.replay(mk("eso", d).with_design(a=1.5), u_ab=u, i_ab=i, T_s=125e-6)

# ---------------------------------------------------------------------------------------
# Stored programs (jax.export): a repeated call skips the tracing; a stale, corrupt or
# mismatched program falls back to a fresh trace; a changed static field gets its own
# ---------------------------------------------------------------------------------------

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402


class _Poly(eqx.Module):
    """A polynomial c0 + c1 x + ... with a static power `k` applied after it."""
    c: jnp.ndarray
    k: int = eqx.field(static=True)


class _Out(eqx.Module):
    y: jnp.ndarray
    total: jnp.ndarray


_TRACES = []


def _poly_fn(p, x, scale):
    _TRACES.append(p.k)  # a Python side effect: runs only when the function is traced
    y = jnp.polyval(p.c[::-1], x) ** p.k * scale
    return _Out(y=y, total=jnp.sum(y))


def _poly_ref(c, x, k, scale):
    y = np.polynomial.polynomial.polyval(x, c) ** k * scale
    return y, y.sum()


@pytest.fixture
def store(tmp_path, monkeypatch):
    d = tmp_path / "exported"
    monkeypatch.setattr(pj.runtime._stored, "_STORE_DIR", d)
    monkeypatch.setattr(pj.runtime._stored, "_LOADED", {})
    _TRACES.clear()
    return d


def _check(out, c, x, k, scale):
    y, total = _poly_ref(np.asarray(c), np.asarray(x), k, scale)
    # a few float64 operations per element: agreement to a few ulps of the values
    np.testing.assert_allclose(np.asarray(out.y), y, rtol=1e-13)
    np.testing.assert_allclose(float(out.total), total, rtol=1e-13)


def test_stored_call_is_off_without_configure(monkeypatch):
    monkeypatch.setattr(pj.runtime._stored, "_STORE_DIR", None)
    p = _Poly(jnp.asarray([1.0, 2.0]), 2)
    assert pj.runtime.stored_call("poly", _poly_fn, (p, jnp.ones(3), 1.0), _Out) is None


def test_stored_program_gives_the_fresh_result_without_tracing(store):
    c, x = jnp.asarray([0.5, -1.0, 0.25]), jnp.linspace(-2.0, 3.0, 7)
    p = _Poly(c, 3)
    out = pj.runtime.stored_call("poly", _poly_fn, (p, x, 2.0), _Out)
    _check(out, c, x, 3, 2.0)
    files = list(store.glob("poly-*.jaxexport"))
    assert len(files) == 1 and len(_TRACES) == 1
    # a new process: nothing loaded yet, the program is read from the file, not traced
    pj.runtime._stored._LOADED.clear()
    c2 = jnp.asarray([1.0, 0.5, -0.75])  # new values of the inputs: same program
    out2 = pj.runtime.stored_call("poly", _poly_fn, (_Poly(c2, 3), x, 2.0), _Out)
    _check(out2, c2, x, 3, 2.0)
    assert len(_TRACES) == 1 and list(store.glob("poly-*.jaxexport")) == files


def test_changed_static_field_or_shape_is_not_served_a_stale_program(store):
    c, x = jnp.asarray([0.5, -1.0, 0.25]), jnp.linspace(-2.0, 3.0, 7)
    pj.runtime.stored_call("poly", _poly_fn, (_Poly(c, 3), x, 2.0), _Out)
    pj.runtime._stored._LOADED.clear()
    out = pj.runtime.stored_call("poly", _poly_fn, (_Poly(c, 2), x, 2.0), _Out)  # k: 3 -> 2
    _check(out, c, x, 2, 2.0)
    out = pj.runtime.stored_call("poly", _poly_fn, (_Poly(c, 2), x, 0.5), _Out)  # static scale
    _check(out, c, x, 2, 0.5)
    out = pj.runtime.stored_call("poly", _poly_fn, (_Poly(c, 2), x[:4], 0.5), _Out)  # shape
    _check(out, c, x[:4], 2, 0.5)
    assert _TRACES == [3, 2, 2, 2] and len(list(store.glob("poly-*.jaxexport"))) == 4


def test_corrupt_or_mismatched_stored_program_falls_back_to_a_trace(store):
    c, x = jnp.asarray([0.5, -1.0, 0.25]), jnp.linspace(-2.0, 3.0, 7)
    args = (_Poly(c, 3), x, 2.0)
    pj.runtime.stored_call("poly", _poly_fn, args, _Out)
    (path,) = store.glob("poly-*.jaxexport")
    for bad in (b"not a program", path.read_bytes()[:100]):
        path.write_bytes(bad)
        pj.runtime._stored._LOADED.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no error and no warning: silently made again
            out = pj.runtime.stored_call("poly", _poly_fn, args, _Out)
        _check(out, c, x, 3, 2.0)
        assert path.stat().st_size > 1000  # written again from the fresh trace
    assert len(_TRACES) == 3
    # a valid program of other input shapes under this call's name (a stale file)
    pj.runtime.stored_call("poly", _poly_fn, (_Poly(c, 3), x[:3], 2.0), _Out)
    other = [p for p in store.glob("poly-*.jaxexport") if p != path]
    path.write_bytes(other[0].read_bytes())
    pj.runtime._stored._LOADED.clear()
    out = pj.runtime.stored_call("poly", _poly_fn, args, _Out)
    _check(out, c, x, 3, 2.0)
    assert len(_TRACES) == 5


def test_unkeyable_static_values_are_not_stored(store):
    p = _Poly(jnp.asarray([1.0, 2.0]), 2)
    fn = lambda p, x: _poly_fn(p, x, 1.0)  # noqa: E731 - a lambda has no stable name
    assert pj.runtime.stored_call("poly", fn, (p, jnp.ones(3)), _Out) is None
    assert not store.exists()


class _Fit(eqx.Module):
    x: jnp.ndarray
    parts: list  # a field that is itself a list of (array, array) pairs


def _lstsq_fn(A, b):
    # QR and an eigensolver: LAPACK custom calls without jax.export's compatibility
    # guarantee (a stored program pins the jaxlib that wrote it)
    q, r = jnp.linalg.qr(A)
    x = jax.scipy.linalg.solve_triangular(r, q.T @ b)
    _TRACES.append("lstsq")
    return _Fit(x=x, parts=[(q, r), (jnp.linalg.eigvalsh(A.T @ A), A @ x - b)])


def test_programs_with_lapack_calls_and_nested_results_are_stored(store):
    """The identification's solve (QR in its Levenberg-Marquardt steps) is stored like
    the analysis: LAPACK's custom calls are allowed, and a result field may be a list of
    pairs. Fed its own committed outputs again, the program read back is compiled once."""
    rng = np.random.default_rng(3)
    A, b = rng.standard_normal((9, 3)), rng.standard_normal(9)
    out = pj.runtime.stored_call("lstsq", _lstsq_fn, (jnp.asarray(A), jnp.asarray(b)), _Fit)
    assert out is not None and len(list(store.glob("lstsq-*.jaxexport"))) == 1
    pj.runtime._stored._LOADED.clear()
    again = pj.runtime.stored_call("lstsq", _lstsq_fn, (jnp.asarray(A), jnp.asarray(b)), _Fit)
    assert _TRACES == ["lstsq"]  # read from the file, not traced again
    ref = np.linalg.lstsq(A, b, rcond=None)[0]
    for o in (out, again):
        np.testing.assert_allclose(np.asarray(o.x), ref, rtol=1e-12)
        (q, r), (ev, res) = o.parts
        np.testing.assert_allclose(np.asarray(q) @ np.asarray(r), A, atol=1e-13)
        np.testing.assert_allclose(np.asarray(ev), np.linalg.eigvalsh(A.T @ A), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(res), A @ ref - b, atol=1e-12)
    # a call whose inputs are an earlier call's outputs (committed arrays) has the
    # signature of one with fresh arrays: one compiled program serves both
    pj.runtime.stored_call("lstsq", _lstsq_fn, (again.parts[0][0], again.x[:0].sum() + b), _Fit)
    (call,) = pj.runtime._stored._LOADED.values()
    assert call._cache_size() == 1


def test_stored_equilibria_equal_a_fresh_trace(store):
    """The CLI's stored analysis (the whole `equilibria`, one exported program) against
    the API's own call, for the LESO at 0.5 p.u. speed with a model mismatch (so the
    non-designed equilibria are not symmetric)."""
    from pmsmjax.analysis import equilibria
    from pmsmjax.analysis._generic import equilibria_stored
    from pmsmjax.observers import make_observer

    drive = pj.preset("zhang750")
    plant = drive.motor
    obs = make_observer("leso", drive, motor=pj.replace_params(drive, L_q=1.2 * plant.L_q).motor)
    w0, i0 = 0.5 * float(drive.w_rated), np.array([0.0, 0.3 * float(drive.base.I_b)])
    ref = jax.device_get(equilibria(obs, plant, w0, i0))
    got = jax.device_get(equilibria_stored(obs, plant, w0, i0))
    assert list(store.glob("equilibria-*.jaxexport"))
    pj.runtime._stored._LOADED.clear()
    again = jax.device_get(equilibria_stored(obs, plant, w0, i0))  # read from the file
    for out in (got, again):
        np.testing.assert_array_equal(out.valid, ref.valid)
        np.testing.assert_array_equal(out.stable, ref.stable)
        assert int(out.status) == int(ref.status) and int(out.n) == int(ref.n)
        v = ref.valid
        # the same computation compiled as another program: only fusion/round-off
        # differences, amplified by the Newton polish's conditioning to far below 1e-9
        np.testing.assert_allclose(out.theta[v], ref.theta[v], rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.x[v], ref.x[v], rtol=1e-9,
                                   atol=1e-9 * np.max(np.abs(ref.x[v])))
        np.testing.assert_allclose(out.jacobian[v], ref.jacobian[v], rtol=1e-9,
                                   atol=1e-9 * np.max(np.abs(ref.jacobian[v])))


def test_changed_source_makes_the_program_again_and_removes_the_old_one(store, monkeypatch):
    c, x = jnp.asarray([0.5, -1.0, 0.25]), jnp.linspace(-2.0, 3.0, 7)
    args = (_Poly(c, 3), x, 2.0)
    monkeypatch.setattr(pj.runtime._stored, "_SOURCE_HASH", "a" * 64)  # the code as it was
    pj.runtime.stored_call("poly", _poly_fn, args, _Out)
    (old,) = store.glob("poly-*.jaxexport")
    monkeypatch.setattr(pj.runtime._stored, "_SOURCE_HASH", "b" * 64)  # the code changed
    pj.runtime._stored._LOADED.clear()
    out = pj.runtime.stored_call("poly", _poly_fn, args, _Out)
    _check(out, c, x, 3, 2.0)
    assert len(_TRACES) == 2  # traced again, not served the old program
    (new,) = store.glob("poly-*.jaxexport")
    assert new != old and not old.exists()


def test_source_hash_covers_the_whole_package(monkeypatch):
    """The key of a stored program hashes every source file of pmsmjax (not only of
    `pmsmjax.runtime`, where the code that hashes them lives)."""
    import hashlib
    from pathlib import Path

    root = Path(pj.__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    monkeypatch.setattr(pj.runtime._stored, "_SOURCE_HASH", None)
    assert pj.runtime._stored._source_hash() == h.hexdigest()
