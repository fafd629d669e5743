"""The earlier home of the shared options, which now have a module each (`_values`,
`_drive_options`, `_output`, `_operating_point`, `_observer_options`). These names stay
importable from here for importers outside the command line that have not moved to
their public names in `pmsmjax.cli` yet."""

from ._drive_options import drive_from_args as drive_from_args
from ._observer_options import (
    ObserverChoice as ObserverChoice,
    observer_from_args as observer_from_args,
)
from ._operating_point import current_from_args as current_from_args
