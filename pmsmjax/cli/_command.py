"""`Command`: what a module of this package gives the registry of commands
(`pmsmjax.cli.__main__`) to be a command."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable


@dataclasses.dataclass(frozen=True)
class Command:
    """One subcommand: its name, help texts, `add_arguments(parser)` and `run(args) ->
    exit status`."""

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
