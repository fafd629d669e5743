"""The resident worker's loop (`serve`): the process that `pmsmjax.runtime._worker`
starts and hands commands to (that module's docstring says what it keeps, what it puts
back between commands and when it stops). `python -m pmsmjax.cli._serve KEY`."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import socket
import sys
import threading
import time

from ..runtime._worker import HEADER, IDLE_S, STATUS, recv_exact, worker_paths


def _streams(tty: tuple[bool, bool, bool]):
    """New `sys.stdin`, `sys.stdout`, `sys.stderr` on descriptors 0, 1, 2, buffered as
    Python buffers its own (line-buffered on a terminal; stderr written through)."""
    import locale

    enc = "utf-8" if sys.flags.utf8_mode else locale.getpreferredencoding(False)
    enc = os.environ.get("PYTHONIOENCODING", "").split(":")[0] or enc
    stdin = io.TextIOWrapper(io.BufferedReader(io.FileIO(0, "r", closefd=False)),
                             encoding=enc)
    stdout = io.TextIOWrapper(io.BufferedWriter(io.FileIO(1, "w", closefd=False)),
                              encoding=enc, line_buffering=tty[1])
    stderr = io.TextIOWrapper(io.BufferedWriter(io.FileIO(2, "w", closefd=False)),
                              encoding=enc, errors="backslashreplace", line_buffering=True,
                              write_through=True)
    return stdin, stdout, stderr


#: After Ctrl-C, the seconds a command may run on before the interrupt is delivered again,
#: and how many times at most: library code that catches every exception can swallow the
#: first one (JAX's bare `except:` around reading an executable's layouts and memory
#: kinds, right after a compile that the Ctrl-C arrived during). The client waits for the
#: command's end, so a swallowed interrupt would leave the command running on. The
#: handler is the worker's own while a command runs: a worker started by a process that
#: ignores SIGINT (a script's background job) inherits the ignoring, and would never see
#: the Ctrl-C its clients forward.
REDELIVER_S = 5.0
REDELIVER_MAX = 3


@contextlib.contextmanager
def _interrupts_repeated():
    """Within the block (the main thread), Ctrl-C raises KeyboardInterrupt, whatever
    SIGINT's handler was before, and again every `REDELIVER_S` while the block has not
    ended, at most `REDELIVER_MAX` times more; the handler is put back after."""
    first: list[float] = []
    ended = threading.Event()

    if threading.current_thread() is not threading.main_thread():
        yield  # signals reach the main thread only
        return

    def on_sigint(signum, frame):
        if ended.is_set():
            return  # a delivery again that came as the block ended
        if not first:
            first.append(time.monotonic())
        raise KeyboardInterrupt

    main = threading.main_thread().ident

    def watch():
        again = 0
        while not ended.wait(0.1):
            if first and again < REDELIVER_MAX and (
                    time.monotonic() - first[0] > REDELIVER_S * (again + 1)):
                again += 1
                # to the main thread, whose system call (a sleep, a wait) it interrupts
                signal.pthread_kill(main, signal.SIGINT)

    previous = signal.signal(signal.SIGINT, on_sigint)
    watcher = threading.Thread(target=watch, name="interrupt-again", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        ended.set()
        watcher.join()
        signal.signal(signal.SIGINT, previous)


def _run_command(argv: list[str]) -> int:
    """One command, as `python -m pmsmjax` would end it: its status, SystemExit's code, or
    a traceback and 1 (130 after Ctrl-C, which is delivered again if the command runs on:
    `_interrupts_repeated`)."""
    import traceback

    from ..cli import main

    try:
        with _interrupts_repeated():
            return int(main(argv) or 0)
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            return e.code or 0
        print(e.code, file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        traceback.print_exc()
        return 130
    except BaseException:  # noqa: BLE001 - reported as Python reports it, the worker lives on
        traceback.print_exc()
        return 1


def _serve_one(conn: socket.socket, finished=None) -> int | None:
    """Take one command from `conn`: its descriptors, arguments, directory and
    environment; run it; put the process back as it was; call `finished()` (the worker's
    information then says the command is done, before the client can read it); send its
    status. Its status, or None if the client had gone (it found the worker busy and ran
    the command itself)."""
    import warnings

    conn.sendall(STATUS.pack(os.getpid()))
    conn.settimeout(5.0)
    msg, fds, _, _ = socket.recv_fds(conn, HEADER.size, 3)
    payload = (recv_exact(conn, HEADER.unpack(msg)[0])
               if len(msg) == HEADER.size and len(fds) == 3 else None)
    if payload is None:
        for fd in fds:
            os.close(fd)
        return None
    conn.settimeout(None)
    request = json.loads(payload)
    saved_fds = [os.dup(k) for k in (0, 1, 2)]
    saved = (sys.stdin, sys.stdout, sys.stderr, sys.argv, os.getcwd(), dict(os.environ),
             os.umask(int(request["umask"])))
    code = 1
    try:
        for k, fd in enumerate(fds):
            os.dup2(fd, k)
            os.close(fd)
        os.environ.clear()
        os.environ.update(request["env"])
        os.chdir(request["cwd"])
        sys.argv = ["pmsmjax", *request["argv"]]
        sys.stdin, sys.stdout, sys.stderr = _streams(tuple(os.isatty(k) for k in (0, 1, 2)))
        with warnings.catch_warnings():  # its filters; entering resets what was shown
            warnings.onceregistry.clear()
            code = _run_command(request["argv"])
    finally:
        for f in (sys.stdout, sys.stderr):
            try:
                f.flush()
            except (OSError, ValueError):
                pass
        sys.stdin, sys.stdout, sys.stderr, sys.argv, cwd, env, umask = saved
        os.umask(umask)
        for k, fd in enumerate(saved_fds):
            os.dup2(fd, k)
            os.close(fd)
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(env)
        if finished is not None:
            try:
                finished()
            except OSError:  # its information file: the status goes to the client all the same
                pass
        try:  # the client ends now; the tidying (seconds, when it drops programs) after,
            conn.sendall(STATUS.pack(code))  # in the loop (`serve`)
        except OSError:
            pass
    return code


def _tidy() -> None:
    """What a command leaves in the process: figures, matplotlib's settings, compiled
    programs beyond half the mapping limit."""
    if "matplotlib" in sys.modules:
        import matplotlib
        import matplotlib.pyplot as plt

        plt.close("all")
        matplotlib.rcParams.update(_MPL_DEFAULTS)
    from ..runtime import release_compiled

    release_compiled(1 / 2)


_MPL_DEFAULTS: dict = {}


def serve(key: str) -> None:
    """The worker's loop (module docstring): bind the socket of `key`, load the command
    line, answer commands one at a time until idle or replaced."""
    sock_path, info_path = worker_paths(key)
    idle_s = float(os.environ.get("PMSMJAX_WORKER_IDLE") or IDLE_S)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    tmp = sock_path.with_name(f".{os.getpid()}.tmp")
    listener.bind(str(tmp))
    listener.listen(8)
    try:
        os.link(tmp, sock_path)  # fails if another worker (or a stale socket) is there
    except FileExistsError:
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(sock_path))
            tmp.unlink()
            return  # another worker serves this key
        except OSError:
            sock_path.unlink(missing_ok=True)  # stale
            os.link(tmp, sock_path)
        finally:
            probe.close()
    tmp.unlink()
    inode = sock_path.stat().st_ino
    # loaded before the first command: what every command imports, and the settings
    import matplotlib

    matplotlib.use("Agg")
    _MPL_DEFAULTS.update(matplotlib.rcParams.copy())
    from ..runtime import configure
    from .__main__ import build_parser

    configure()
    build_parser()
    served = 0
    interrupted = False
    started = last = time.time()

    from .._files import atomic_write

    def write_info(busy_since=None):  # read by `pmsmjax worker` at any moment
        atomic_write(info_path, json.dumps({
            "pid": os.getpid(), "key": key, "python": sys.executable, "started": started,
            "last_command": last, "commands": served, "idle_s": idle_s,
            "busy_since": busy_since}))

    write_info()
    info_path.with_suffix(".starting").unlink(missing_ok=True)  # clients stop waiting
    listener.settimeout(1.0)
    try:
        while True:
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                try:
                    replaced = sock_path.stat().st_ino != inode
                except OSError:
                    replaced = True
                if replaced or time.time() - last > idle_s:
                    return
                continue
            except KeyboardInterrupt:  # a client's late Ctrl-C
                continue
            code, done = None, []
            write_info(busy_since=time.time())

            def finished():
                # before the client has its status: the count it may read is this
                # command's, and a client that comes next finds no command running
                # (it waits for the tidying)
                nonlocal served, last
                served, last = served + 1, time.time()
                write_info()
                done.append(True)

            try:
                with conn:
                    code = _serve_one(conn, finished)
            except (OSError, ValueError, KeyboardInterrupt):
                pass
            if not done:  # the client had gone, or the command's set-up failed
                last = time.time()
                write_info()
            if code is not None:
                _tidy()
            if code == 130:
                # interrupted: a computation may still run in XLA's threads, and the
                # process's state is not known; the next command starts a new worker
                interrupted = True
                return
    finally:
        listener.close()
        try:
            ours = sock_path.stat().st_ino == inode
        except OSError:
            ours = True  # removed: `pmsmjax worker --stop`
        if ours:
            sock_path.unlink(missing_ok=True)
            info_path.unlink(missing_ok=True)
            log = info_path.with_suffix(".log")
            if log.exists() and log.stat().st_size == 0:
                log.unlink()
        if interrupted:
            os._exit(0)  # without waiting for the interrupted computation


if __name__ == "__main__":
    serve(sys.argv[1])
