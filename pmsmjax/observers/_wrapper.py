"""The shared part of the observers that wrap another one (`FlyingCatch`,
`SpeedFromAngle`): the wrapped observer's machine model, design and analysis, passed
through.

A wrapper changes what the drive does with the observer (when it starts, which speed it
hands over), not the observer's error dynamics, so its analysis is the wrapped
observer's. Its `motor` is the wrapped observer's machine model, kept on the wrapper so
that `simulate`'s `observer_scale` and `with_motor` (which replace `observer.motor`)
reach the observer that runs (`_inner`).
"""

from __future__ import annotations

import equinox as eqx

from .._plant._params import PMSMParams
from ._base import AbstractObserver


class WrappedObserver(AbstractObserver):
    """Base of the observers that wrap `observer` (see the module docstring). A subclass
    implements `init`, `step` and `_rewrap(observer)` (the same wrapper around another
    observer)."""

    observer: eqx.AbstractVar[AbstractObserver]
    motor: eqx.AbstractVar[PMSMParams]

    @staticmethod
    def _check_wrapped(owner: str, observer, cls) -> None:
        if not isinstance(observer, AbstractObserver) or isinstance(observer, cls):
            raise ValueError(f"`{owner}(observer=...)` must be an observer (not a "
                             f"{owner}); got {type(observer).__name__}.")

    def _inner(self) -> AbstractObserver:
        """The wrapped observer with this wrapper's machine model (None for an observer
        without one, e.g. `SensoredObserver`)."""
        return eqx.tree_at(lambda o: o.motor, self.observer, self.motor,
                           is_leaf=lambda x: x is None)

    def _rewrap(self, observer: AbstractObserver) -> WrappedObserver:
        raise NotImplementedError

    @property
    def coordinates(self):
        return self.observer.coordinates

    @property
    def design_units(self):
        return self.observer.design_units

    @property
    def extras(self):
        return self.observer.extras

    @property
    def angle_dependent(self):
        return self.observer.angle_dependent

    @property
    def equilibria_starts(self):
        return self.observer.equilibria_starts

    @property
    def equilibria_gauss_newton(self):
        return self.observer.equilibria_gauss_newton

    # --- design and analysis: the wrapped observer's -----------------------------------
    @classmethod
    def from_drive(cls, drive, *, motor: PMSMParams | None = None, **design):
        raise ValueError(f"`{cls.__name__}` wraps an observer: `{cls.__name__}("
                         "make_observer(name, drive))`.")

    def design_parameters(self) -> dict:
        return self.observer.design_parameters()

    def with_design(self, **values):
        return self._rewrap(self.observer.with_design(**values))

    def with_motor(self, motor: PMSMParams):
        return self._rewrap(self.observer.with_motor(motor))

    def with_magnetic(self, magnetic):
        return self._rewrap(self._inner().with_magnetic(magnetic))

    def error_rhs(self, x, op, plant):
        return self._inner().error_rhs(x, op, plant)

    def error_scale(self, op, plant):
        return self._inner().error_scale(op, plant)

    def error_state(self, state, truth, plant):
        return self._inner().error_state(state.inner, truth, plant)

    def observer_state(self, x, truth, plant):
        raise ValueError(f"`{type(self).__name__}.observer_state`: analyse the wrapped "
                         "observer (`.observer`).")

    def designed_error(self, op, plant):
        return self._inner().designed_error(op, plant)
