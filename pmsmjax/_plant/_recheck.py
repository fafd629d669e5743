"""Construction checks run again on modules copied without them (`eqx.tree_at`): above both
`pmsmjax._validate` (the checks) and the machine parameters (which it leaves alone), so that
neither imports the other."""

from __future__ import annotations

import dataclasses

import equinox as eqx

from .._validate import is_concrete
from ._params import PMSMParams


def recheck(tree) -> None:
    """Run the construction checks (`__check_init__`, every class's in the MRO, as
    equinox does) of each equinox module in `tree` again on its current values. Copies
    made with `eqx.tree_at` (`with_design`, `with_motor`) skip them; a run that traces
    the values (`pmsmjax._sim._batching.values_as_arrays`) calls this first, so that a bad
    concrete value still raises, naming the argument. A module holding a traced value
    (inside `jit` or `vmap`) is not checked here: its values cannot be read. Nor is a
    machine model (`PMSMParams`): it is checked where it is built, and a model derived
    from it (`scale_motor`, a sensitivity sweep) may leave the constructor's ranges on
    purpose (a resistance-free estimator model), which the runs handle."""
    def visit(x):
        if isinstance(x, PMSMParams):
            return
        if isinstance(x, eqx.Module) and is_concrete(x):
            for cls in reversed(type(x).__mro__):
                check = cls.__dict__.get("__check_init__")
                if check is not None:
                    check(x)
        if isinstance(x, eqx.Module):
            for f in dataclasses.fields(x):
                visit(getattr(x, f.name, None))
        elif isinstance(x, list | tuple):
            for v in x:
                visit(v)
        elif isinstance(x, dict):
            for v in x.values():
                visit(v)

    visit(tree)
