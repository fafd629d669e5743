"""`pmsmjax` and `python -m pmsmjax`: the command line, `pmsmjax.cli`, run in the resident
worker when one takes the command (`pmsmjax.runtime._worker`), else in this process."""

import sys


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default `sys.argv[1:]`); its exit status."""
    from pmsmjax.runtime._worker import run_or_serve

    return run_or_serve(argv)


if __name__ == "__main__":
    sys.exit(main())
