"""Position and speed observers. All share `AbstractObserver`'s `init`/`step` interface."""

from ._base import (
    AbstractObserver as AbstractObserver,
    Estimate as Estimate,
    Measurement as Measurement,
    SensoredObserver as SensoredObserver,
)
