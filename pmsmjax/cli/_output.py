"""Where a command's results go: `--out DIR` (a folder, left as it was when the command
fails: `out_dir_transaction`), `--no-plot`, `--json` (strict JSON on stdout,
`print_json`), and the first line of its console (`first_line`). The JSON files are
written by `pmsmjax._files.write_json`, the one writer of the library and its
commands."""

from __future__ import annotations

import argparse
import contextlib
import os

from .._files import json_text
from ._values import CLIError


def add_output_options(parser: argparse.ArgumentParser, default_out: str | None, *,
                       plot: bool = True, out_help: str | None = None):
    """`--out DIR` (required if `default_out` is None) and, with `plot`, `--no-plot`;
    returns the group."""
    g = parser.add_argument_group("output")
    if out_help is not None:
        g.add_argument("--out", default=default_out, metavar="DIR", help=out_help)
    elif default_out is None:
        g.add_argument("--out", required=True, metavar="DIR",
                       help="output directory (created if missing)")
    else:
        g.add_argument("--out", default=default_out, metavar="DIR",
                       help="output directory, created if missing (default: %(default)s)")
    if plot:
        g.add_argument("--no-plot", action="store_true", help="do not write the PNG figure")
    return g


def add_json_option(group) -> None:
    group.add_argument("--json", action="store_true",
                       help="print the result as JSON only (strict JSON: NaN becomes null) "
                            "instead of a table")


@contextlib.contextmanager
def out_dir_transaction(path: str | None):
    """Leave nothing half-written in the output folder `path` when the block fails: every
    file the block created or changed in it is removed again (and the folder itself if
    the block created it), then the exception propagates. Files that were there before and
    that the block did not touch stay, and so do the files under the folders given to
    `keep_on_failure` (a sweep's finished chunks)."""
    if not path:
        yield
        return
    existed = os.path.isdir(path)

    def snapshot():
        out = {}
        for root, _, files in os.walk(path):
            for f in files:
                q = os.path.join(root, f)
                try:
                    st = os.stat(q)
                except OSError:
                    continue
                out[q] = (st.st_mtime_ns, st.st_size)
        return out

    before = snapshot() if existed else {}
    _KEEP.clear()
    try:
        yield
    except BaseException:
        if os.path.isdir(path):
            for q, sig in snapshot().items():
                if before.get(q) != sig and not _kept(q):
                    with contextlib.suppress(OSError):
                        os.remove(q)
            for root, dirs, _ in os.walk(path, topdown=False):
                for d in dirs:
                    with contextlib.suppress(OSError):
                        os.rmdir(os.path.join(root, d))  # only empty ones
            if not existed:
                with contextlib.suppress(OSError):
                    os.rmdir(path)
        raise


#: Folders whose files a failing `out_dir_transaction` keeps (`keep_on_failure`).
_KEEP: set[str] = set()


def keep_on_failure(path: str) -> None:
    """Keep the files under `path` when the command fails or is interrupted inside
    `out_dir_transaction`: a sweep's finished chunks, which the next run resumes from."""
    _KEEP.add(os.path.abspath(path))


def _kept(path: str) -> bool:
    q = os.path.abspath(path)
    return any(q == k or q.startswith(k + os.sep) for k in _KEEP)


def prepare_out_dir(path: str) -> str:
    if os.path.exists(path) and not os.path.isdir(path):
        raise CLIError(f"--out {path!r} exists and is not a directory")
    os.makedirs(path, exist_ok=True)
    return path


def print_json(obj) -> None:
    """Print `obj` on stdout as indented, strict JSON (non-finite numbers become null)."""
    print(json_text(obj))


def first_line(command: str, motor: str, observer: str, *details: str) -> str:
    """The first console line of a command that runs or analyses an observer:
    `pmsmjax COMMAND: motor ...; observer ...; details...`, with the drive of
    `motor_text` and the observer of `ObserverChoice.describe`."""
    return f"pmsmjax {command}: " + "; ".join((motor, observer, *details))
