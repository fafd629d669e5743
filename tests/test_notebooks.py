"""Execute every notebook in notebooks/ (new notebooks are picked up automatically).

Each notebook runs in its own temporary working directory, so anything it writes stays out
of the repository, with matplotlib's `Agg` backend. The notebooks run inside the test
worker, in an IPython shell with a fresh namespace per notebook (`_run_cells`): the
suite is compile-bound, and a worker already holds the programs its tests compiled and
has imported JAX and pmsmjax, where a kernel of its own would start, import and compile
again. One notebook (`KERNEL_NOTEBOOK`) still runs in a Jupyter kernel started as a user's
is (jupyter_client starts the `python3` kernelspec, whose command is `python` with the
running interpreter, `sys.executable`, so under `.venv/bin/python -m pytest` the kernel
uses the virtual environment), so that the path users take stays tested.
"""

import os
import pathlib
import sys
import warnings
from unittest import mock

import matplotlib
import matplotlib.pyplot as plt
import nbclient
import nbformat
import pytest


NOTEBOOKS = sorted((pathlib.Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))
TIMEOUT_S = 600
#: The notebook that runs in a real Jupyter kernel (the smallest one).
KERNEL_NOTEBOOK = "01_sensored_drive.ipynb"


def test_kernel_is_this_interpreter():
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    spec = KernelSpecManager().get_kernel_spec("python3")
    assert spec.language == "python"
    cmd = KernelManager(kernel_name="python3").format_kernel_cmd()
    assert os.path.realpath(cmd[0]) == os.path.realpath(sys.executable), cmd


def test_notebooks_found():
    assert NOTEBOOKS, "no notebooks found in notebooks/"
    assert KERNEL_NOTEBOOK in [p.name for p in NOTEBOOKS]


def _run_in_kernel(nb, tmp_path):
    client = nbclient.NotebookClient(
        nb, timeout=TIMEOUT_S, kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
    )
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors


def _shell():
    """The worker's IPython shell (one per process: IPython keeps a single instance)."""
    from IPython.core.interactiveshell import InteractiveShell
    from traitlets.config import Config

    class Shell(InteractiveShell):
        def enable_gui(self, gui=None):  # `%matplotlib inline` needs no event loop
            pass

    if not InteractiveShell.initialized():
        config = Config()
        config.HistoryManager.enabled = False
        Shell.instance(config=config)
    return InteractiveShell.instance()


def _reset(shell):
    """A fresh namespace (`shell.reset(new_session=True)`) without IPython's forced full
    garbage collection (its `displayhook.flush()` calls `gc.collect()`): in a worker that
    has compiled thousands of programs a full collection scans millions of objects, 1-2 s
    per reset. The notebook's objects die with the namespace as before; cyclic garbage
    waits for the collector's next regular pass."""
    with mock.patch("gc.collect", lambda *args, **kwargs: 0):
        shell.reset(new_session=True)


def _run_cells(nb, name):
    """Every code cell of `nb` in order, in an IPython shell (magics such as
    `%matplotlib inline` work) with a fresh namespace; the first failing cell fails the
    test with its exception. Warnings are shown as in a kernel, not raised (the suite
    turns them into errors), and matplotlib's backend and figures are restored after."""
    shell = _shell()
    _reset(shell)
    backend = matplotlib.get_backend()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            for k, cell in enumerate(nb.cells):
                if cell.cell_type != "code":
                    continue
                result = shell.run_cell(cell.source, store_history=False, silent=True)
                error = result.error_before_exec or result.error_in_exec
                if error is not None:
                    raise AssertionError(f"{name}, cell {k}:\n{cell.source}") from error
    finally:
        _reset(shell)
        plt.close("all")
        matplotlib.use(backend)


@pytest.mark.timeout(2 * TIMEOUT_S)
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.chdir(tmp_path)
    nb = nbformat.read(path, as_version=4)
    if path.name == KERNEL_NOTEBOOK:
        _run_in_kernel(nb, tmp_path)
    else:
        _run_cells(nb, path.name)


def test_a_failing_cell_fails_the_run_and_namespaces_do_not_leak():
    """The in-worker runner fails on the first failing cell, naming the notebook and the
    cell, and each notebook starts from an empty namespace."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_markdown_cell("text"), nbformat.v4.new_code_cell("x = 1"),
                nbformat.v4.new_code_cell("assert x == 2, 'the claim'")]
    with pytest.raises(AssertionError, match="a.ipynb, cell 2") as failed:
        _run_cells(nb, "a.ipynb")
    assert str(failed.value.__cause__) == "the claim"
    nb.cells = [nbformat.v4.new_code_cell("y = x")]
    with pytest.raises(AssertionError, match="b.ipynb, cell 0") as failed:
        _run_cells(nb, "b.ipynb")
    assert isinstance(failed.value.__cause__, NameError)
