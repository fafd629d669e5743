"""Stability and design analysis of any observer (generic over the observer contract):
linearisation, equilibria, feasibility maps over any two design parameters, Lyapunov
(slowly-varying) certificates, and a chunked, sharded, resumable runner for large sweeps.
zhang2022's closed forms (the quartic (34)-(36)) are fast paths next to the generic route."""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports
from ..observers import OperatingPoint as OperatingPoint
from ._classify import DesignClass as DesignClass, classify as classify
from ._dead_time import (
    dead_time_angle_error as dead_time_angle_error,
    dead_time_resistance as dead_time_resistance,
)
from ._discrete import (
    discrete_error_map as discrete_error_map,
    discrete_error_run as discrete_error_run,
    discrete_jacobian as discrete_jacobian,
    discrete_poles as discrete_poles,
)
from ._equilibria import Equilibria as Equilibria, eso_equilibria as eso_equilibria
from ._feasibility import (
    FeasibilityMap as FeasibilityMap,
    classify_designs as classify_designs,
    design_map as design_map,
    feasibility_map as feasibility_map,
)
from ._floquet import Floquet as Floquet, floquet as floquet
from ._frequency import (
    bemf_response as bemf_response,
    bode_data as bode_data,
    discrete_bemf_system as discrete_bemf_system,
    g_c_leso as g_c_leso,
    g_fa_leso as g_fa_leso,
    g_gi_leso as g_gi_leso,
    routh_complex2 as routh_complex2,
)
from ._generic import (
    STATUS_DEGENERATE as STATUS_DEGENERATE,
    STATUS_NONE as STATUS_NONE,
    STATUS_OK as STATUS_OK,
    Stability as Stability,
    equilibria as equilibria,
    equilibria_traced as equilibria_traced,
    linearization as linearization,
    stability as stability,
)
from ._harmonic import (
    harmonic_ripple as harmonic_ripple,
    input_matrix as input_matrix,
)
from ._linearize import (
    charpoly as charpoly,
    eso_linearization as eso_linearization,
    eso_rhs as eso_rhs,
    is_hurwitz as is_hurwitz,
    linearize as linearize,
    max_real_eig as max_real_eig,
    routh_hurwitz as routh_hurwitz,
)
from ._lock import (
    LockBasin as LockBasin,
    lock_basin as lock_basin,
    lock_time as lock_time,
)
from ._noise import SensorNoise as SensorNoise, sensor_noise as sensor_noise
from ._quartic import (
    quartic_coefficients as quartic_coefficients,
    quartic_equilibria as quartic_equilibria,
    quartic_t_coefficients as quartic_t_coefficients,
    trig_poly as trig_poly,
)
from ._saturated import (
    VERDICTS as VERDICTS,
    SaturatedPoint as SaturatedPoint,
    apparent_plant as apparent_plant,
    incremental_plant as incremental_plant,
    saturated_map as saturated_map,
    saturated_operating_point as saturated_operating_point,
)
from ._sweep import ChunkInfo as ChunkInfo, run_sweep as run_sweep
from ._sweep_grid import SweepGrid as SweepGrid, grid_product as grid_product


# Loaded on first use (`pmsmjax._lazy`): the certificates import optimistix, and their
# validation by simulation diffrax.
if TYPE_CHECKING:
    from ._lyapunov import (
        LyapunovCertificate as LyapunovCertificate,
        lyapunov_solve as lyapunov_solve,
        slowly_varying_certificate as slowly_varying_certificate,
    )
    from ._ramp import (
        RampRun as RampRun,
        fastest_converging_ramp as fastest_converging_ramp,
        simulate_ramp as simulate_ramp,
    )

__getattr__, __dir__ = lazy_exports(__name__, __file__, globals())
