"""The `pmsmjax` command line (`pmsmjax COMMAND [options]`, also `python -m pmsmjax`).

`main(argv)` runs it; the parser and the registry of commands are in
`pmsmjax.cli.__main__`, the shared options in `_options.py`, one module per command.
"""


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default `sys.argv[1:]`); return the exit status
    (0 success, 1 the run failed, 2 bad input)."""
    # imported here, not at the top, so that `python -m pmsmjax.cli` runs the module
    # `__main__` once (as `__main__`) instead of also importing it as a submodule
    from .__main__ import main as run

    return run(argv)


from .._data._files import (  # noqa: E402
    atomic_write as atomic_write,
    json_safe as json_safe,
    write_json as write_json,
)
