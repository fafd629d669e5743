"""The resident worker (`pmsmjax.runtime._worker`): a command run through it prints,
writes and exits as the same command run in a process of its own; a busy worker leaves
the command to the client; Ctrl-C interrupts the command and ends the worker; a worker
serves only processes with its interpreter, source tree and start-up settings."""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from pmsmjax.runtime import _worker


@pytest.fixture
def worker_env():
    # a short folder: a socket's path is limited to about 100 bytes, which pytest's
    # temporary folders under xdist exceed
    sockets = Path(tempfile.mkdtemp(prefix="pmsmjax-w"))
    # the environment of a user's shell: without the variables that importing JAX (in
    # this test process) sets, which `pmsmjax worker --start` must not count either
    env = {k: v for k, v in os.environ.items()
           if k not in ("TF_CPP_MIN_LOG_LEVEL", "TPU_SKIP_MDS_QUERY")}
    env.update(PMSMJAX_WORKER="1", PMSMJAX_WORKER_DIR=str(sockets),
               PMSMJAX_WORKER_IDLE="120")
    # Ctrl-C as in a user's terminal: the processes started here inherit an ignored
    # SIGINT from this one otherwise (something in the suite leaves it ignored in the
    # test worker at times; a client that ignores it never forwards it)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield env
    if previous is not None:  # None: a handler not set from Python, left as it is
        signal.signal(signal.SIGINT, previous)
    for sock in sockets.glob("*.sock"):
        sock.unlink()  # its worker stops within a second
    time.sleep(1.5)
    shutil.rmtree(sockets, ignore_errors=True)


def _pmsmjax(args, env, cwd, **kw):
    return subprocess.run([sys.executable, "-m", "pmsmjax", *args], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=300, **kw)


def _info(env) -> list[dict]:
    folder = env["PMSMJAX_WORKER_DIR"]
    rows = []
    for f in sorted(os.listdir(folder)):
        if f.endswith(".json"):
            try:
                with open(os.path.join(folder, f)) as fh:
                    rows.append(json.loads(fh.read()))
            except (OSError, ValueError):  # being written or removed
                pass
    return rows


def test_commands_in_the_worker_equal_commands_in_their_own_process(worker_env, tmp_path):
    alone = dict(worker_env, PMSMJAX_WORKER="0")
    first = _pmsmjax(["equilibria", "--json"], worker_env, tmp_path)  # runs here, leaves one
    assert first.returncode == 0, first.stderr
    # the next command comes at once: it waits for the worker still loading
    cases = [
        (["equilibria", "--json", "--observer", "leso", "--speed", "0.5"], "80", 0),
        (["equilibria", "--observer", "nope"], "80", 2),  # bad input: one line on stderr
        (["--help"], "60", 0),  # the environment reaches the command: --help wraps at
        (["--help"], "150", 0),  # the client's COLUMNS
    ]
    for args, columns, code in cases:
        env_w, env_a = (dict(e, COLUMNS=columns) for e in (worker_env, alone))
        w, a = _pmsmjax(args, env_w, tmp_path), _pmsmjax(args, env_a, tmp_path)
        assert (w.returncode, w.stdout, w.stderr) == (a.returncode, a.stdout, a.stderr)
        assert w.returncode == code
    info = _info(worker_env)[0]
    assert info["commands"] == len(cases)  # all of them in the worker
    # files land in the client's working directory, with the same numbers
    (tmp_path / "w").mkdir()
    (tmp_path / "a").mkdir()
    run = ["simulate", "--t-end", "0.05", "--out", "out", "--no-plot"]

    # the client's file mode mask reaches the command too (set here and inherited: a
    # `preexec_fn` would fork this process, which JAX warns against)
    mask = os.umask(0o027)
    try:
        w = _pmsmjax(run, worker_env, tmp_path / "w")
        a = _pmsmjax(run, alone, tmp_path / "a")
    finally:
        os.umask(mask)
    assert w.returncode == a.returncode == 0, (w.stderr, a.stderr)
    modes = {os.stat(tmp_path / d / "out/trajectory.npz").st_mode & 0o777 for d in "wa"}
    assert modes == {0o640}, modes
    assert _info(worker_env)[0]["commands"] == len(cases) + 1
    with np.load(tmp_path / "w/out/trajectory.npz", allow_pickle=False) as fw, \
            np.load(tmp_path / "a/out/trajectory.npz", allow_pickle=False) as fa:
        assert sorted(fw.files) == sorted(fa.files)
        for k in fw.files:
            np.testing.assert_array_equal(fw[k], fa[k])
    # standard input is the client's
    piped = _pmsmjax(["convert", "--help"], worker_env, tmp_path, input="ignored")
    assert piped.returncode == 0 and "usage: pmsmjax convert" in piped.stdout
    listed = _pmsmjax(["worker"], worker_env, tmp_path)
    assert f"pid {info['pid']}:" in listed.stdout
    stopped = _pmsmjax(["worker", "--stop"], worker_env, tmp_path)
    assert "stopped 1 worker(s)" in stopped.stdout
    assert _info(worker_env) == []


def test_a_busy_worker_leaves_the_command_to_the_client_and_ctrl_c_ends_it(worker_env,
                                                                          tmp_path):
    started = _pmsmjax(["worker", "--start"], worker_env, tmp_path)
    assert started.returncode == 0 and "takes commands" in started.stdout, started.stderr
    pid = _info(worker_env)[0]["pid"]
    long = subprocess.Popen([sys.executable, "-m", "pmsmjax", "simulate", "--t-end", "5000",
                             "--out", "long", "--no-plot"], env=worker_env, cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    end = time.time() + 60
    while not _info(worker_env)[0]["busy_since"]:
        assert time.time() < end, "the worker did not take the long command"
        time.sleep(0.1)
    busy = _pmsmjax(["equilibria", "--json"], worker_env, tmp_path)
    assert busy.returncode == 0 and json.loads(busy.stdout)["command"] == "equilibria"
    row = _info(worker_env)[0]
    assert row["busy_since"] and row["commands"] == 0  # it ran in the client
    long.send_signal(signal.SIGINT)
    _, err = long.communicate(timeout=60)
    assert long.returncode == 130, err
    assert "KeyboardInterrupt" in err
    end = time.time() + 30
    while time.time() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("the interrupted worker did not stop")
    assert _info(worker_env) == [] and not list(
        Path(worker_env["PMSMJAX_WORKER_DIR"]).glob("*.sock"))


def test_the_worker_key_follows_the_start_up_settings(monkeypatch):
    base = {"HOME": "/h", "XLA_FLAGS": "--a", "PMSMJAX_CACHE_DIR": "/c"}
    key = _worker.worker_key(base)
    assert _worker.worker_key(dict(base, HOME="/other", PMSMJAX_WORKER_IDLE="5",
                                   JAX_ENABLE_X64="0")) == key
    for change in ({"XLA_FLAGS": "--b"}, {"PMSMJAX_CACHE_DIR": "/d"},
                   {"JAX_PLATFORMS": "cpu"}, {"PYTHONPATH": "/p"}):
        assert _worker.worker_key(dict(base, **change)) != key, change
    rows = _worker._source_fingerprint()
    assert any(r[0].endswith(os.path.join("runtime", "_worker.py")) for r in rows)
    monkeypatch.setattr(_worker, "_source_fingerprint", lambda: rows[:-1])
    assert _worker.worker_key(base) != key  # an edited source tree: another worker
    open_dir = Path(tempfile.mkdtemp(prefix="pmsmjax-o"))  # short: see `worker_env`
    os.chmod(open_dir, 0o755)
    monkeypatch.setenv("PMSMJAX_WORKER_DIR", str(open_dir))
    with pytest.raises(PermissionError, match="mode 0700"):
        _worker.socket_dir()
    open_dir.rmdir()
    monkeypatch.setenv("PMSMJAX_WORKER", "maybe")  # a named error, not a traceback
    assert _worker.run_or_serve(["--version"]) == 2
    monkeypatch.setenv("PMSMJAX_WORKER_DIR", "/tmp/" + "x" * 80)
    with pytest.raises(OSError, match="too long for a Unix socket"):
        _worker.socket_dir()


def test_import_pmsmjax_loads_no_jax_and_still_gives_float64():
    """The client hands a command over without JAX: `import pmsmjax` loads none of it,
    and float64 is on once JAX comes (through a name of pmsmjax, or imported first), with
    the user's `JAX_ENABLE_X64` back in the environment; the same with quick compiles,
    whose JAX option also waits for JAX (it once imported JAX with pmsmjax)."""
    code = (
        "import os, sys\n"
        "import pmsmjax\n"
        "assert 'jax' not in sys.modules, sorted(m for m in sys.modules if 'jax' in m)\n"
        "import pmsmjax.runtime._worker\n"
        "assert 'jax' not in sys.modules and 'numpy' not in sys.modules\n"
        "pmsmjax.FOC\n"
        "import jax.numpy as jnp\n"
        "assert jnp.ones(2).dtype == jnp.float64\n"
        "import jax\n"
        "print(os.environ.get('JAX_ENABLE_X64'),\n"
        "      os.environ.get('JAX_TRACEBACK_IN_LOCATIONS_LIMIT'),\n"
        "      jax.config.jax_traceback_in_locations_limit == 0)\n")
    for before, quick, shown in ((None, "0", "None None False"), ("0", "0", "0 None False"),
                                 (None, "1", "None None True"), ("0", "1", "0 None True")):
        env = {k: v for k, v in os.environ.items()
               if k not in ("JAX_ENABLE_X64", "JAX_TRACEBACK_IN_LOCATIONS_LIMIT")}
        env["PMSMJAX_QUICK_COMPILE"] = quick
        if before is not None:
            env["JAX_ENABLE_X64"] = before
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == shown
    first = subprocess.run([sys.executable, "-c", "import jax, pmsmjax, jax.numpy as jnp; "
                            "print(jnp.ones(1).dtype)"], capture_output=True, text=True,
                           timeout=120)
    assert first.stdout.strip() == "float64", first.stderr


def test_a_client_waits_for_a_worker_that_has_bound_its_socket_but_is_still_loading(
        tmp_path, monkeypatch):
    """A worker binds its socket first (to hold its key) and accepts commands only once
    loaded; until then its `.starting` file stands. A client that comes in between waits
    for it instead of running the command itself (before: it found the socket, no answer
    within half a second and no information file, took the worker for busy and ran the
    command itself)."""
    import socket as so
    import threading

    sockets = Path(tempfile.mkdtemp(prefix="pmsmjax-w"))
    monkeypatch.setenv("PMSMJAX_WORKER_DIR", str(sockets))
    key = "loading"
    sock_path, info_path = _worker.worker_paths(key)
    listener = so.socket(so.AF_UNIX, so.SOCK_STREAM)
    listener.bind(str(sock_path))
    listener.listen(8)
    starting = info_path.with_suffix(".starting")
    starting.write_text(f"{os.getpid()} {time.time()}")
    LOAD_S = 1.5
    got = {}

    def worker():  # loads, then takes commands; connections made meanwhile were dropped
        time.sleep(LOAD_S)
        starting.unlink()
        while True:
            conn, _ = listener.accept()
            with conn:
                try:
                    conn.sendall(_worker.STATUS.pack(os.getpid()))
                    conn.settimeout(2.0)
                    msg, fds, _, _ = so.recv_fds(conn, _worker.HEADER.size, 3)
                except OSError:
                    continue
                for fd in fds:
                    os.close(fd)
                if len(msg) < _worker.HEADER.size:
                    continue  # a client that had given up
                got.update(json.loads(_worker.recv_exact(conn, _worker.HEADER.unpack(msg)[0])))
                conn.sendall(_worker.STATUS.pack(7))
                return

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    t0 = time.time()
    try:
        assert _worker.run_in_worker(["equilibria"], key) == 7  # the worker's status
    finally:
        listener.close()
        shutil.rmtree(sockets, ignore_errors=True)
    assert time.time() - t0 >= LOAD_S and got["argv"] == ["equilibria"]
    thread.join(5)


def test_an_interrupt_that_library_code_swallows_is_delivered_again(monkeypatch):
    """Ctrl-C while a command compiles can land in library code that catches every
    exception (JAX's bare `except:` right after a compile): the worker delivers it again
    while the command runs on, so the command still ends with 130. A worker that
    inherited an ignored SIGINT (started from a script's background job) takes it all
    the same, and leaves the signal as it found it."""
    import threading

    import pmsmjax.cli
    from pmsmjax.cli import _serve

    swallowed = []

    def command(argv):
        try:
            time.sleep(10)  # the Ctrl-C arrives here ...
        except:  # noqa: E722 - ... and is swallowed, as by a bare except
            swallowed.append(True)
        time.sleep(20)  # without a second delivery the command runs on to its end
        return 0

    monkeypatch.setattr(pmsmjax.cli, "main", command)
    monkeypatch.setattr(_serve, "REDELIVER_S", 0.5)
    previous = signal.getsignal(signal.SIGINT)
    try:
        for inherited in (signal.default_int_handler, signal.SIG_IGN):
            signal.signal(signal.SIGINT, inherited)
            swallowed.clear()
            threading.Timer(0.3, signal.pthread_kill, (threading.main_thread().ident,
                                                       signal.SIGINT)).start()
            t0 = time.monotonic()
            assert _serve._run_command(["simulate"]) == 130, inherited
            assert swallowed and time.monotonic() - t0 < 5.0, inherited
            assert signal.getsignal(signal.SIGINT) is inherited  # put back
    finally:
        signal.signal(signal.SIGINT, previous)
