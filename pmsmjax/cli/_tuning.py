"""`pmsmjax tune` and `pmsmjax compare` (`_tune.py`, `_compare.py`): the gain tuner and the
observer comparison of the `tuning` package, under the one command line.

`tuning` imports `pmsmjax`, never the reverse: these commands import it only when they
run (`handover`), so `import pmsmjax` and every other command never load it. Their
options are the `tuning` parsers' own (`tuning.__main__.build_parser`,
`tuning.compare.cli.build_parser`), shown by `pmsmjax tune --help` and `pmsmjax compare
--help`; `python -m tuning` and `python -m tuning compare` run the same code.
"""

from __future__ import annotations

import argparse

from ._command import Command
from ._values import CLIError


#: The commands handed over to `tuning`, and what they run.
HANDOVER = {"tune": "tuning.__main__", "compare": "tuning.compare.cli"}


def tuning_module(name: str):
    """The `tuning` module that runs the command `name` (imported now)."""
    import importlib

    try:
        return importlib.import_module(HANDOVER[name])
    except ModuleNotFoundError as e:
        raise CLIError(f"pmsmjax {name}: the `tuning` package is not importable ({e}); "
                       f"install pmsmjax from its source tree (`pip install -e .`)"
                       ) from None


def handover(name: str, argv: list[str]) -> int:
    """Run `pmsmjax NAME ARGV...` (NAME in `HANDOVER`) with the `tuning` package."""
    module = tuning_module(name)
    try:
        return module.main(list(argv), prog=f"pmsmjax {name}")
    except SystemExit as e:  # --help (0), or argparse's bad option (2, message printed)
        return e.code if isinstance(e.code, int) else 0


def handover_command(name: str, help: str, description: str) -> Command:
    """The `Command` `name` (in `HANDOVER`): its arguments are the `tuning` parser's,
    shown by its own `--help`."""

    def add_arguments(p: argparse.ArgumentParser) -> None:
        p.add_argument("args", nargs=argparse.REMAINDER, metavar="...",
                       help=f"the options of `pmsmjax {name} --help`")

    return Command(name=name, help=help, description=description,
                   add_arguments=add_arguments,
                   run=lambda args: handover(name, args.args))
