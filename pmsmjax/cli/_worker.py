"""`pmsmjax worker`: the resident workers that run later commands (`pmsmjax.runtime._worker`):
list them, or stop them."""

from __future__ import annotations

import argparse
import json
import os
import time

from ..runtime import _worker
from ._command import Command
from ._values import CLIError


def _arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--start", action="store_true",
                   help="start a worker for this environment now and wait until it takes "
                        "commands (a script's first command is then fast too)")
    g.add_argument("--stop", action="store_true",
                   help="stop every worker of this user (each finishes its command first)")


def _start(timeout_s: float = 120.0) -> int:
    if not _worker.enabled():
        raise CLIError("PMSMJAX_WORKER=0: the resident worker is off in this environment")
    key = _worker.worker_key()  # as a command's client computes it
    _worker.start_worker(key, _worker.start_environ())
    info = _worker.socket_dir() / f"{key}.json"
    end = time.time() + timeout_s
    while not info.exists():
        if time.time() > end:
            print(f"pmsmjax worker: no worker answered within {timeout_s:.0f} s (its log: "
                  f"{info.with_suffix('.log')})")
            return 1
        time.sleep(0.05)
    print(f"worker pid {json.loads(info.read_text())['pid']} takes commands "
          f"({_worker.socket_dir()})")
    return 0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _workers() -> list[dict]:
    rows = []
    for info in sorted(_worker.socket_dir().glob("*.json")):
        try:
            row = json.loads(info.read_text())
        except (OSError, ValueError):
            continue
        if _alive(int(row["pid"])):
            rows.append(row)
        else:  # ended without tidying (killed): its files go
            info.unlink(missing_ok=True)
            info.with_suffix(".sock").unlink(missing_ok=True)
    return rows


def _run(args: argparse.Namespace) -> int:
    if args.start:
        return _start()
    rows = _workers()
    where = _worker.socket_dir()
    if args.stop:
        for row in rows:
            (where / f"{row['key']}.sock").unlink(missing_ok=True)  # it stops within 1 s
        end = time.time() + 5.0
        while time.time() < end and any(_alive(int(r["pid"])) for r in rows):
            time.sleep(0.1)
        left = [r for r in rows if _alive(int(r["pid"]))]
        print(f"stopped {len(rows) - len(left)} worker(s)"
              + (f"; still running a command: pid {', '.join(str(r['pid']) for r in left)}"
                 if left else ""))
        return 0
    state = "on" if _worker.enabled() else "off (PMSMJAX_WORKER=0)"
    print(f"resident workers: {state}; sockets in {where}")
    now = time.time()
    for row in rows:
        state = (f"running a command for {now - row['busy_since']:.0f} s"
                 if row.get("busy_since") else f"idle {now - row['last_command']:.0f} s")
        print(f"  pid {row['pid']}: {row['commands']} command(s), up {now - row['started']:.0f} "
              f"s, {state} (stops after {row['idle_s']:.0f} s idle), {row['python']}")
    if not rows:
        print("  none running (the next command starts one when it ends)")
    return 0


COMMAND = Command(
    name="worker",
    help="list, start or stop the resident workers that run later commands",
    description="A command run as `pmsmjax ...` hands itself to a resident worker (a "
                "process that keeps JAX and the compiled programs loaded), or runs itself "
                "and then starts one in the background. A worker stops after "
                "PMSMJAX_WORKER_IDLE seconds without a command (default 900). Lists them, "
                "starts one now (--start) or stops them (--stop). PMSMJAX_WORKER=0 runs "
                "every command in its own process.",
    add_arguments=_arguments,
    run=_run,
)
