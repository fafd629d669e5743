"""pmsmjax: differentiable JAX simulator, analyser and gain tuner for sensorless PMSM drives.

Importing pmsmjax enables float64 in JAX (analysis needs it); pass float32 arrays (or
cast a PyTree with `astype`) for bulk sweeps in single precision.
"""

import importlib.metadata
from typing import TYPE_CHECKING

from ._lazy import lazy_exports
from .runtime._settings import apply_xla_flags, enable_x64, settle_jax_env


# The process-wide settings a library import makes: analysis needs float64, and the XLA
# flags of fast single runs go into XLA_FLAGS while JAX's backend has not started (a
# one-time warning otherwise; `pmsmjax.runtime`). The compilation cache belongs to the
# entry points, which call `pmsmjax.runtime.configure()`. Both without importing JAX:
# every name below loads on first use (`pmsmjax._lazy`), so that `import pmsmjax` costs
# milliseconds and a command loads what it needs (the command line's client, which hands
# a command to a resident worker, loads nothing of JAX).
enable_x64()
apply_xla_flags(stacklevel=3)

if TYPE_CHECKING:
    from . import (
        analysis as analysis,
        observers as observers,
        papers as papers,
        runtime as runtime,
    )
    from ._control._controllers import (
        CurrentController as CurrentController,
        SpeedController as SpeedController,
    )
    from ._control._dtp import (
        DualCurrentControl as DualCurrentControl,
        XYCurrentController as XYCurrentController,
    )
    from ._control._foc import FOC as FOC
    from ._control._limits import (
        CurrentRefs as CurrentRefs,
        limit_vector as limit_vector,
        mtpa_i_d as mtpa_i_d,
    )
    from ._control._saturated import MTPATable as MTPATable
    from ._control._startup import IfStartup as IfStartup
    from ._data._convert import (
        ConvertedLog as ConvertedLog,
        LogFormatError as LogFormatError,
        convert_log as convert_log,
    )
    from ._data._flying_start import (
        FlyingStart as FlyingStart,
        flying_start as flying_start,
        unknown_start as unknown_start,
    )
    from ._data._gains_table import (
        GAINS_TABLE_FILES as GAINS_TABLE_FILES,
        TabulatedDesign as TabulatedDesign,
        apply_gains_table as apply_gains_table,
        check_gains_table as check_gains_table,
        gains_speed_grid as gains_speed_grid,
        gains_table_constant as gains_table_constant,
        gains_table_scheduled as gains_table_scheduled,
        load_gains_table as load_gains_table,
        low_speed_text as low_speed_text,
        speed_loop_text as speed_loop_text,
        verdict_text as verdict_text,
        verdict_warning as verdict_warning,
        write_gains_table as write_gains_table,
    )
    from ._data._identifiable import IDENTIFIABLE as IDENTIFIABLE
    from ._data._identify import (
        ExcitationWarning as ExcitationWarning,
        IdentifiabilityWarning as IdentifiabilityWarning,
        IdentifyError as IdentifyError,
        IdentifyResult as IdentifyResult,
        identify as identify,
    )
    from ._data._log_checks import (
        EncoderCheck as EncoderCheck,
        estimate_encoder_offset as estimate_encoder_offset,
        recording_warnings as recording_warnings,
    )
    from ._data._log_layout import (
        LogLayout as LogLayout,
        load_log_layout as load_log_layout,
    )
    from ._data._recording import (
        RecordedData as RecordedData,
        load_recording as load_recording,
        save_recording as save_recording,
    )
    from ._data._replay import (
        initial_estimate as initial_estimate,
        replay as replay,
        replay_estimates as replay_estimates,
    )
    from ._frames import (
        J as J,
        angle_error as angle_error,
        clarke as clarke,
        clarke0 as clarke0,
        inv_clarke as inv_clarke,
        inv_park as inv_park,
        inv_vsd as inv_vsd,
        jmul as jmul,
        park as park,
        rot_matrix as rot_matrix,
        rotate as rotate,
        vsd as vsd,
        vsd_matrix as vsd_matrix,
        wrap_angle as wrap_angle,
    )
    from ._plant._fluxmap_file import (
        FluxMapError as FluxMapError,
        FluxMapReport as FluxMapReport,
        check_flux_map as check_flux_map,
        read_flux_map as read_flux_map,
    )
    from ._plant._inverter import (
        dead_time_error_ab as dead_time_error_ab,
        dead_time_fundamental as dead_time_fundamental,
    )
    from ._plant._magnetic import (
        AbstractMagneticModel as AbstractMagneticModel,
        AlgebraicSaturation as AlgebraicSaturation,
        FluxMap as FluxMap,
        constant_model as constant_model,
    )
    from ._plant._motor import PMSM as PMSM, PlantInput as PlantInput, PlantState as PlantState
    from ._plant._motorfile import (
        MOTOR_FILE_SCHEMA as MOTOR_FILE_SCHEMA,
        MotorFileError as MotorFileError,
        load_motor_file as load_motor_file,
        parse_motor_file as parse_motor_file,
    )
    from ._plant._motorfile_write import (
        motor_file_text as motor_file_text,
        save_motor_file as save_motor_file,
    )
    from ._plant._params import (
        BaseValues as BaseValues,
        Drive as Drive,
        DualThreePhaseParams as DualThreePhaseParams,
        EMFHarmonics as EMFHarmonics,
        Inverter as Inverter,
        Mechanics as Mechanics,
        PMSMParams as PMSMParams,
        replace_params as replace_params,
        scale_motor as scale_motor,
    )
    from ._plant._presets import (
        PRESET_NAMES as PRESET_NAMES,
        ipm3k5_saturation as ipm3k5_saturation,
        preset as preset,
    )
    from ._sim._dtypes import astype as astype
    from ._sim._integrate import RK4 as RK4, integrate as integrate
    from ._sim._metrics import (
        LOCK_ACQUIRE_S as LOCK_ACQUIRE_S,
        LOCK_DEG as LOCK_DEG,
        LOCK_DWELL_S as LOCK_DWELL_S,
        STATIC_WINDOW as STATIC_WINDOW,
        error_stats as error_stats,
        lock_status as lock_status,
        replay_stats as replay_stats,
        run_errors as run_errors,
        run_metrics as run_metrics,
        settled_mask as settled_mask,
        settling_time as settling_time,
        static_window as static_window,
        trajectory_metrics as trajectory_metrics,
    )
    from ._sim._plant_run import PlantTrace as PlantTrace, run_plant as run_plant
    from ._sim._scenario import Profile as Profile, Scenario as Scenario
    from ._sim._simulate import Sensing as Sensing, simulate as simulate
    from ._sim._solution import RESULTS as RESULTS, Trajectory as Trajectory
    from ._validate import NonFiniteInputError as NonFiniteInputError
    from .observers import (
        AbstractObserver as AbstractObserver,
        AFOObserver as AFOObserver,
        ESODesign as ESODesign,
        ESOObserver as ESOObserver,
        Estimate as Estimate,
        FixedGains as FixedGains,
        FlyingCatch as FlyingCatch,
        LESOObserver as LESOObserver,
        Measurement as Measurement,
        ParallelModelObserver as ParallelModelObserver,
        RotorFluxObserver as RotorFluxObserver,
        SensoredObserver as SensoredObserver,
        SpeedFromAngle as SpeedFromAngle,
    )

__getattr__, __dir__ = lazy_exports(__name__, __file__, globals(), settle_jax_env)


try:
    __version__ = importlib.metadata.version("pmsmjax")
except importlib.metadata.PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"
