"""One registry of observers by name, used by `simulate`'s callers, `replay`, the analysis
commands and the tuner.

Every registered class implements the whole `AbstractObserver` contract, including
`from_drive(drive, *, motor=None, **design)`, the paper's default design for any motor
preset. `make_observer(name, drive, ...)` is the one place a name becomes an observer.
"""

from __future__ import annotations

from .._plant._magnetic import AbstractMagneticModel
from .._plant._params import Drive, PMSMParams
from ._base import AbstractObserver


_REGISTRY: dict[str, type[AbstractObserver]] = {}


def register_observer(name: str, cls: type[AbstractObserver] | None = None):
    """Register `cls` under `name` (lower case); usable as a decorator
    `@register_observer("name")`. Re-registering a name replaces it."""
    def deco(c):
        if not (isinstance(c, type) and issubclass(c, AbstractObserver)):
            raise ValueError(f"`register_observer({name!r}, ...)` needs an "
                             f"`AbstractObserver` subclass; got {c!r}.")
        _REGISTRY[name.lower()] = c
        return c
    return deco if cls is None else deco(cls)


def observer_names() -> tuple[str, ...]:
    """Names of the registered observers, in registration order."""
    return tuple(_REGISTRY)


def observer_class(name: str) -> type[AbstractObserver]:
    """The class registered as `name` (`ValueError` listing the names otherwise)."""
    key = str(name).lower()
    if key not in _REGISTRY:
        raise ValueError(f"Unknown observer {name!r}; choose one of "
                         f"{', '.join(_REGISTRY)}.")
    return _REGISTRY[key]


#: The drive an observer without a paper drive (`paper_motor` None) runs on, and its
#: sampling period (s): zhang2022's 750 W drive.
DEFAULT_PAPER_DRIVE = ("zhang750", 125e-6)


def paper_drive(name: str) -> tuple[str, float]:
    """`(preset name, T_s in s)` of the drive the observer registered as `name` is
    demonstrated on: its class's `paper_motor` and `paper_T_s` (`DEFAULT_PAPER_DRIVE` for
    what it leaves None). The tuner, the benchmarks, the tests and the docs figures ask
    this, so that a new observer states its drive once, in its class."""
    cls = observer_class(name)
    motor, T_s = DEFAULT_PAPER_DRIVE
    if cls.paper_motor is not None:
        motor = cls.paper_motor
        T_s = cls.paper_T_s if cls.paper_T_s is not None else T_s
    return motor, float(T_s)


def make_observer(name: str, drive: Drive, *, motor: PMSMParams | None = None,
                  magnetic: AbstractMagneticModel | None = None,
                  **design) -> AbstractObserver:
    """The observer registered as `name` with its default design for `drive`.

    **Arguments:**

    - `name`: a registered name (`observer_names()`), e.g. `"eso"`, `"leso"`, `"afo"`.
    - `drive`: the `Drive` whose machine the observer models.
    - `motor`: the observer's machine model, replacing the drive's (observer-model
      mismatch); SI `PMSMParams`.
    - `magnetic`: a magnetic model (e.g. the drive's own map, `drive.motor.magnetic`) on
      which the observer schedules its model at the measured current
      (`AbstractObserver.with_magnetic`); default None: the constant model `motor`.
    - `design`: design parameters by name (the class's `design_units`), e.g. `w2=300.0`.
    """
    if not isinstance(drive, Drive):
        raise ValueError(f"`make_observer(drive=...)` must be a `Drive` (e.g. "
                         f"`pj.preset('zhang750')`); got {type(drive).__name__}.")
    obs = observer_class(name).from_drive(drive, motor=motor, **design)
    return obs if magnetic is None else obs.with_magnetic(magnetic)
