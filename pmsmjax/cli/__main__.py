"""The `pmsmjax` command line: the parser, the registry of commands, `main`.

Every command is a module of this package that defines `COMMAND`, a `Command` with its
name, help texts, `add_arguments(parser)` and `run(args) -> exit status`;
`COMMAND_MODULES` below lists the modules, one line each, and `build_parser` makes one
argparse subparser per command. A new command is its module and its line there. The
options that several commands share are defined once, a module per idea (`_values`,
`_drive_options`, `_output`, `_operating_point`, `_observer_options`, `_sweep_options`).
`tune` and `compare` hand over to the `tuning` package, imported only when they run
(`_tuning.py`).

Errors in the inputs (a bad file, a bad `--set`, an unknown motor or observer, an invalid
option value) end the command with exit status 2 and a one-line message on stderr, without
a traceback. Exit status 1: the command ran but its result is a failure (a diverged run, a
degenerate analysis, no certificate).
"""

from __future__ import annotations

import argparse
import importlib
import sys

import pmsmjax as pj

from . import _tuning
from ._command import Command
from ._output import out_dir_transaction
from ._values import CLIError


#: The modules of the commands, in the order `pmsmjax --help` lists them; each defines
#: `COMMAND`.
COMMAND_MODULES = (
    "_simulate",
    "_plant",
    "_replay",
    "_identify",
    "_convert",
    "_feasibility",
    "_equilibria",
    "_certify",
    "_cache",
    "_worker",
    "_response",
    "_export_c",
    "_motor",
    "_gains",
    "_tune",
    "_compare",
)

#: The commands, by name, in that order.
COMMANDS: dict[str, Command] = {
    command.name: command
    for command in (importlib.import_module(f".{m}", __package__).COMMAND
                    for m in COMMAND_MODULES)
}


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise CLIError(f"{self.prog}: error: {message} (see `{self.prog} --help`)")


class _RootParser(_Parser):
    def parse_args(self, args=None, namespace=None):
        """argparse's, with an unknown option named by the command it was given to
        (`pmsmjax feasibility: error: unrecognized arguments: ...`)."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            command = getattr(ns, "command", None)
            prog = f"{self.prog} {command}" if command else self.prog
            raise CLIError(f"{prog}: error: unrecognized arguments: {' '.join(extras)} (see "
                           f"`{prog} --help`)")
        return ns


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subparser per command (the observer choices are read
    from the registry `pmsmjax.observers` each time)."""
    parser = _RootParser(
        prog="pmsmjax",
        description="Differentiable PMSM drive simulator: command-line front end. "
                    "Run `pmsmjax COMMAND --help` for the options of each command.",
    )
    parser.add_argument("--version", action="version", version=f"pmsmjax {pj.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=_Parser)
    for cmd in COMMANDS.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.description)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default `sys.argv[1:]`); return the exit status.

    0 = success, 1 = the run finished but failed (e.g. diverged), 2 = bad input.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in _tuning.HANDOVER:  # `tuning` parses and runs these itself
        try:
            return _tuning.handover(argv[0], argv[1:])
        except CLIError as e:
            print(_one_line(e), file=sys.stderr)
            return 2
    pj.runtime.configure()  # process settings of an entry point, before any computation
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except CLIError as e:
        print(_one_line(e), file=sys.stderr)
        return 2
    except SystemExit as e:  # --help, --version
        return e.code if isinstance(e.code, int) else 0
    try:
        with out_dir_transaction(getattr(args, "out", None)):
            return int(args._run(args))
    except (CLIError, ValueError, OSError) as e:
        print(f"pmsmjax {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
