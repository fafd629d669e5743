"""The resident worker of the command line: a process that keeps JAX, pmsmjax and every
program it has compiled in memory, and runs the `pmsmjax` commands that later processes
hand to it.

**Why a worker, not serialised executables.** A warm command (its programs in the
persistent compilation cache) spends most of its time before it computes anything:
starting Python and importing JAX, equinox and the command's modules (about 1.3 s on a
2-core machine), then tracing or loading its programs. The compilation cache and the
stored programs (`stored_call`) already remove XLA's compile and the tracing of the
analyses; what is left is the import, which no file format removes. A process that has
done it once and stays removes it for every later command.

**How a command reaches it** (`run_or_serve`, the console script `pmsmjax` and `python
-m pmsmjax`; the worker's own loop is `pmsmjax.cli._serve`). The client imports nothing
of JAX: it connects to the worker's Unix socket, hands it its standard input, output and
error (the file descriptors themselves, so that progress bars, terminal widths, pipes and
child processes behave as in the client), its arguments, working directory, file mode
mask and environment, and waits for the exit status. Ctrl-C in
the client interrupts the command in the worker, which then stops (a computation may still
run in XLA's threads; the next command starts a new worker). It runs one command at a time:
a client that finds it busy (no answer within `BUSY_WAIT_S`), or finds none, runs the
command itself, and afterwards starts a worker in the background for the next one; a
client that finds one still loading (started less than `START_WAIT_S` ago), or tidying up
after its last command (`TIDY_WAIT_S`), waits for it.

**Which worker.** One per Python interpreter, pmsmjax source tree (every file's size and
modification time: an edited or upgraded pmsmjax starts a new worker) and process
settings (the environment variables that JAX, XLA, Python and pmsmjax read at start-up:
`worker_key`). Its socket lives in a directory only the user can open (`socket_dir`).
It stops after `PMSMJAX_WORKER_IDLE` seconds without a command (default 900), when
its socket is removed, or with `pmsmjax worker --stop`.

**Between commands** the worker puts back what a command may change of the process: the
working directory, the environment, `sys.argv`, the standard streams, warning filters and
the warnings already shown, matplotlib's settings and figures; and drops its compiled
programs when the memory mappings pass half the system's limit (`release_compiled`).
Commands that join a multi-process JAX run (`--coordinator`, `--num-processes`,
`--process-id`) always run in the client.

`PMSMJAX_WORKER=0` turns the worker off (every command in its own process, as before);
the test suite does so, except for the tests of this module.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import stat
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ._settings import _env_flag, start_environ


#: Seconds a client waits for a worker to take its command before it runs it itself.
BUSY_WAIT_S = 0.5
#: Seconds a client waits for a worker that runs no command (it is tidying up after the
#: last one: dropping compiled programs takes seconds on a loaded machine).
TIDY_WAIT_S = 10.0
#: Seconds after its start during which a loading worker is waited for.
START_WAIT_S = 15.0
#: Seconds without a command after which a worker stops (`PMSMJAX_WORKER_IDLE`).
IDLE_S = 900.0
#: Environment variables that fix a process's settings at start-up: a client whose
#: values differ uses another worker.
KEY_PREFIXES = ("JAX_", "XLA_", "PMSMJAX_", "PYTHON", "TF_", "CUDA_", "TPU_", "MPL",
                "OMP_", "OPENBLAS_", "MKL_", "LD_")
#: Options that join a multi-process run (`pmsmjax.cli._sweep_options`): never in a worker.
IN_CLIENT_OPTIONS = ("--coordinator", "--num-processes", "--process-id")
#: The longest socket folder: a Unix socket's path has at most 107 bytes on Linux (103
#: on macOS), and the socket's own name takes 30 (`<key>.sock`).
_MAX_DIR = 72
#: The protocol: a request's length before its JSON (sent with the three descriptors);
#: the worker's pid (its answer on connect) and the command's exit status.
HEADER = struct.Struct("!Q")
STATUS = struct.Struct("!i")


def enabled() -> bool:
    """Whether commands use a resident worker (`PMSMJAX_WORKER`, on unless 0; off where
    the system cannot pass file descriptors over a Unix socket, e.g. Windows)."""
    return _env_flag("PMSMJAX_WORKER", True) and hasattr(socket, "send_fds") and hasattr(
        socket, "AF_UNIX")


def socket_dir() -> Path:
    """The directory of this user's worker sockets: `PMSMJAX_WORKER_DIR`, else
    `$XDG_RUNTIME_DIR/pmsmjax`, else `pmsmjax-UID` in the temporary directory. Created
    with mode 0700; one that another user owns, or others may open, is refused."""
    if os.environ.get("PMSMJAX_WORKER_DIR"):
        d = Path(os.environ["PMSMJAX_WORKER_DIR"]).expanduser()
    elif os.environ.get("XDG_RUNTIME_DIR"):
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "pmsmjax"
    else:
        d = Path(tempfile.gettempdir()) / f"pmsmjax-{os.getuid()}"
    if len(os.fsencode(d)) > _MAX_DIR:
        raise OSError(f"worker directory {d} is too long for a Unix socket path "
                      f"({len(os.fsencode(d))} bytes; at most {_MAX_DIR}): set "
                      "PMSMJAX_WORKER_DIR to a shorter one")
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = d.stat()
    if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
        raise PermissionError(f"worker directory {d} must belong to this user with mode "
                              f"0700 (it has uid {st.st_uid}, mode "
                              f"{oct(stat.S_IMODE(st.st_mode))})")
    return d


def _source_fingerprint() -> list:
    """Every Python file of pmsmjax and tuning: path, size, modification time."""
    rows = []
    here = Path(__file__).resolve().parents[1]
    for package in (here, here.parent / "tuning"):
        for root, dirs, files in os.walk(package):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__")
            for f in sorted(files):
                if f.endswith(".py"):
                    st = os.stat(os.path.join(root, f))
                    rows.append((os.path.join(root, f), st.st_size, st.st_mtime_ns))
    return rows


def worker_key(env: dict | None = None) -> str:
    """The identity of a worker that may run this process's commands (module docstring):
    the interpreter, the source tree and the start-up settings in `env` (default: the
    environment before pmsmjax and JAX set anything, `start_environ`)."""
    env = start_environ() if env is None else env
    settings = sorted((k, v) for k, v in env.items()
                      if k.startswith(KEY_PREFIXES) and not k.startswith("PMSMJAX_WORKER")
                      and k != "JAX_ENABLE_X64")  # pmsmjax sets float64 in every process
    blob = json.dumps([sys.executable, sys.version, sys.flags.optimize, settings,
                       _source_fingerprint()])
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def worker_paths(key: str) -> tuple[Path, Path]:
    """The socket and the information file (pid, commands served, ...) of worker `key`."""
    d = socket_dir()
    return d / f"{key}.sock", d / f"{key}.json"


# ---------------------------------------------------------------------------------------
# The client


def recv_exact(sock: socket.socket, n: int) -> bytes | None:
    """`n` bytes from `sock`, or None if it closed first."""
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


def _connect(path: Path, timeout: float = BUSY_WAIT_S) -> tuple[socket.socket, int] | None:
    """A connection to the worker at `path` that has taken it (its pid) within `timeout`
    seconds, or None: no worker, or one busy with another command."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(timeout)
        s.connect(str(path))
        hello = recv_exact(s, STATUS.size)
        if hello is None:
            s.close()
            return None
        s.settimeout(None)
        return s, STATUS.unpack(hello)[0]
    except OSError:  # no socket, a stale one, or a busy worker (timeout)
        s.close()
        return None


def _running_command(key: str) -> bool:
    """Whether the worker of `key` says that it runs a command (its information file;
    when that cannot be read, it is taken to be busy)."""
    try:
        info = json.loads(worker_paths(key)[1].read_text())
    except (OSError, ValueError):
        return True
    return info.get("busy_since") is not None


def _starting(key: str) -> bool:
    """Whether a worker of `key` was started less than `START_WAIT_S` ago and is still
    loading (`start_worker` leaves a `.starting` file with its pid; the worker removes it
    when it takes commands)."""
    path = worker_paths(key)[1].with_suffix(".starting")
    try:
        pid, started = (float(x) for x in path.read_text().split())
        os.kill(int(pid), 0)
    except (OSError, ValueError):
        return False
    return time.time() - started < START_WAIT_S


def run_in_worker(argv: list[str], key: str) -> int | None:
    """Run the command `argv` in the worker of `key`; its exit status, or None when no
    worker took it (the caller runs it). A worker still loading is waited for: it is
    ready sooner than this process would have imported what the command needs."""
    sock_path, _ = worker_paths(key)
    conn = _connect(sock_path)
    # a loading worker has bound its socket already (to hold the key) but accepts only
    # once loaded (its `.starting` file is gone then): wait for it, socket or not
    while conn is None and _starting(key):
        time.sleep(0.05)
        conn = _connect(sock_path)
    if conn is None and sock_path.exists() and not _running_command(key):
        conn = _connect(sock_path, TIDY_WAIT_S)  # it is tidying up after the last one
    if conn is None:
        return None
    s, pid = conn
    with s:
        for f in (sys.stdout, sys.stderr):
            f.flush()
        umask = os.umask(0)
        os.umask(umask)
        payload = json.dumps({"argv": argv, "cwd": os.getcwd(), "umask": umask,
                              "env": dict(os.environ)}).encode()
        try:
            socket.send_fds(s, [HEADER.pack(len(payload))], [0, 1, 2])
            s.sendall(payload)
        except OSError:
            return None  # it went away before it started the command
        interrupted = False
        while True:
            try:
                status = recv_exact(s, STATUS.size)
                break
            except KeyboardInterrupt:  # Ctrl-C: interrupt the command, wait for its end
                if interrupted:
                    return 130
                interrupted = True
                try:
                    os.kill(pid, signal.SIGINT)
                except OSError:
                    return 130
    if status is None:
        print("pmsmjax: the resident worker stopped during the command (run it again, or "
              "with PMSMJAX_WORKER=0 in a process of its own)", file=sys.stderr)
        return 1
    return STATUS.unpack(status)[0]


def start_worker(key: str, env: dict) -> subprocess.Popen | None:
    """Start a worker for `key` in the background (its own session, no terminal), with
    the environment `env`; None if one already answers."""
    sock_path, info_path = worker_paths(key)
    if sock_path.exists():
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(sock_path))
            return None  # alive (busy or not)
        except OSError:
            pass
        finally:
            probe.close()
    # the worker imports this pmsmjax wherever it was started from (a checkout without
    # installation too); its commands get the client's environment back
    here = str(Path(__file__).resolve().parents[2])
    env = dict(env, PYTHONPATH=os.pathsep.join(
        [here] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]))
    if _starting(key):
        return None  # another client started one a moment ago
    log = open(info_path.with_suffix(".log"), "ab")
    try:
        p = subprocess.Popen(
            [sys.executable, "-m", "pmsmjax.cli._serve", key], env=env,
            stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True,
            cwd=str(socket_dir()))
    finally:
        log.close()
    info_path.with_suffix(".starting").write_text(f"{p.pid} {time.time()}")
    return p


def run_or_serve(argv: list[str] | None = None) -> int:
    """The console script: run `argv` (default `sys.argv[1:]`) in the resident worker
    if one takes it, else here, then leave a worker for the next command (module
    docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        on = enabled()
    except ValueError as e:
        print(f"pmsmjax: {e}", file=sys.stderr)
        return 2
    use = on and (not argv or argv[0] != "worker") and not any(
        a.split("=")[0] in IN_CLIENT_OPTIONS for a in argv)
    key = env = None
    if use:
        env = start_environ()
        try:
            key = worker_key(env)
            code = run_in_worker(argv, key)
        except OSError as e:  # no usable socket directory: run here
            print(f"pmsmjax: resident worker unavailable ({e}); PMSMJAX_WORKER=0 silences "
                  "this", file=sys.stderr)
            key = code = None
        if code is not None:
            return code
    from ..cli import main

    try:
        return main(argv)
    finally:
        if key is not None:
            try:
                start_worker(key, env)
            except OSError:
                pass
