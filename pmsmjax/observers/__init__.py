"""Position and speed observers. All implement the `AbstractObserver` contract; the
registry (`make_observer`, `observer_names`) is the one place a name becomes one."""

from .._control._limits import (
    d_current_feedforward as d_current_feedforward,  # stumper (48), a control law
)
from ._back_emf_leso import (
    AbstractBackEMFLESO as AbstractBackEMFLESO,
    LESOState as LESOState,
)
from ._base import (
    AbstractObserver as AbstractObserver,
    ErrorCoordinates as ErrorCoordinates,
    Estimate as Estimate,
    Measurement as Measurement,
    OperatingPoint as OperatingPoint,
    PlantPoint as PlantPoint,
    SensoredObserver as SensoredObserver,
)
from ._catch import CatchState as CatchState, FlyingCatch as FlyingCatch
from ._eso import (
    AbstractFluxObserver as AbstractFluxObserver,
    AFOObserver as AFOObserver,
    ESOObserver as ESOObserver,
    FluxObserverState as FluxObserverState,
    LESOObserver as LESOObserver,
)
from ._eso_design import (
    ESOGains as ESOGains,
    error_dynamics as error_dynamics,
    error_matrix as error_matrix,
    error_signal as error_signal,
    eso_gains as eso_gains,
    fal as fal,
    gain_G1 as gain_G1,
    gains_g23 as gains_g23,
    gains_pi as gains_pi,
    psi_a as psi_a,
    sigma1 as sigma1,
    zhang38 as zhang38,
)
from ._eso_schedules import (
    AbstractGainSchedule as AbstractGainSchedule,
    ESODesign as ESODesign,
    FixedGains as FixedGains,
)
from ._li_leso import (
    CLESOObserver as CLESOObserver,
    FALESOObserver as FALESOObserver,
    GILESOObserver as GILESOObserver,
)
from ._nonlinear_flux import (
    NonlinearFluxObserver as NonlinearFluxObserver,
    NonlinearFluxState as NonlinearFluxState,
)
from ._parallel_model import (
    ParallelModelObserver as ParallelModelObserver,
    ParallelModelState as ParallelModelState,
    backemf_polar as backemf_polar,
    parallel_model_angle as parallel_model_angle,
)
from ._parallel_model_sensitivity import (
    parallel_model_angle_printed as parallel_model_angle_printed,
    parallel_model_offset as parallel_model_offset,
    parallel_model_offsets_printed as parallel_model_offsets_printed,
    parallel_model_sensitivity as parallel_model_sensitivity,
)
from ._pll import QuadraturePLL as QuadraturePLL
from ._reduced_order import (
    ReducedOrderObserver as ReducedOrderObserver,
    ReducedOrderState as ReducedOrderState,
)
from ._registry import (
    DEFAULT_PAPER_DRIVE as DEFAULT_PAPER_DRIVE,
    make_observer as make_observer,
    observer_class as observer_class,
    observer_names as observer_names,
    paper_drive as paper_drive,
    register_observer as register_observer,
)
from ._rotor_flux import (
    RotorFluxObserver as RotorFluxObserver,
    RotorFluxState as RotorFluxState,
)
from ._speed_tracker import (
    W_TRACK as W_TRACK,
    W_TRACK_HZ as W_TRACK_HZ,
    SpeedFromAngle as SpeedFromAngle,
    TrackerState as TrackerState,
)
from ._wrapper import WrappedObserver as WrappedObserver


register_observer("eso", ESOObserver)
register_observer("leso", LESOObserver)
register_observer("afo", AFOObserver)
register_observer("parallel-model", ParallelModelObserver)
register_observer("rotor-flux", RotorFluxObserver)
register_observer("c-leso", CLESOObserver)
register_observer("gi-leso", GILESOObserver)
register_observer("fa-leso", FALESOObserver)
register_observer("reduced-order", ReducedOrderObserver)
register_observer("nonlinear-flux", NonlinearFluxObserver)
