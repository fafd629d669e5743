"""The `pmsmjax` command line (`pmsmjax COMMAND [options]`, also `python -m pmsmjax`).

`main(argv)` runs it; the parser and the registry of commands are in
`pmsmjax.cli.__main__`, one module per command. The options that several commands share
are defined once, a module per idea: `_values` (argument types, `CLIError`),
`_drive_options` (the drive), `_output` (the output folder, JSON on stdout),
`_operating_point` and `_observer_options` (the analysis commands' operating point and
every command's observer), `_sweep_options` (the large sweeps).

The names below are what other packages (`tuning`, whose `pmsmjax tune` and `pmsmjax
compare` share these options) use of it.
"""

from .._files import (
    atomic_write as atomic_write,
    json_safe as json_safe,
    write_json as write_json,
)
from ._drive_options import (
    add_drive_options as add_drive_options,
    drive_from_args as drive_from_args,
)
from ._observer_options import (
    ObserverChoice as ObserverChoice,
    add_speed_from_angle_option as add_speed_from_angle_option,
    observer_from_args as observer_from_args,
)
from ._operating_point import current_from_args as current_from_args
from ._output import out_dir_transaction as out_dir_transaction
from ._sweep_options import (
    add_sweep_options as add_sweep_options,
    init_distributed as init_distributed,
    sweep_settings as sweep_settings,
)
from ._values import CLIError as CLIError, ListOption as ListOption, finite_float as finite_float


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default `sys.argv[1:]`); return the exit status
    (0 success, 1 the run failed, 2 bad input)."""
    # imported here, not at the top, so that `python -m pmsmjax.cli` runs the module
    # `__main__` once (as `__main__`) instead of also importing it as a submodule
    from .__main__ import main as run

    return run(argv)
