"""References written without pmsmjax, which the throughput benchmarks time pmsmjax
against and check it with.

- `closed_loop.c`: the closed loop of `benchmarks.throughput.simulate` as scalar C
  (`build_c` compiles it with `gcc -O3 -march=native` into `results/benchmarks/build/`,
  float64 and float32, each also with OpenMP over the drives; `c_simulate` calls it
  through ctypes); `build_c(observer=...)` builds the sensorless loop with the observer
  step that `pmsmjax.firmware.export_c` generates;
- `closed_loop_numpy.py`: the same algorithm on batched NumPy arrays;
- `feasibility_numpy.py`: zhang2022's feasibility classification (Fig. 1) with
  NumPy/SciPy, point by point and batched (`benchmarks.throughput.feasibility`).
"""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np


HERE = Path(__file__).resolve().parent
BUILD = HERE.parents[1] / "results" / "benchmarks" / "build"

#: Plain numbers the C step reads (`closed_loop.c`'s `params_t`, in its order).
C_PARAMS = ("R_s", "L_d", "L_q", "psi_f", "n_p", "J", "B",
            "cR_s", "cL_d", "cL_q", "cpsi_f", "alpha_c", "u_max", "J_over_np", "alpha_s",
            "tau_max", "i_d_ref", "i_max", "k_tau",
            "T_s", "t_ramp", "t_load", "tau_load", "i_bound", "w_bound")


class _CParams(ctypes.Structure):
    _fields_ = [(n, ctypes.c_double) for n in C_PARAMS] + [("n_sub", ctypes.c_int)]


#: The C builds: name -> extra gcc flags.
C_BUILDS = {
    "float64": ["-DREAL=double"],
    "float32": ["-DREAL=float"],
    "float64_omp": ["-DREAL=double", "-fopenmp"],
    "float32_omp": ["-DREAL=float", "-fopenmp"],
}


def build_c(verbose: bool = True, observer=None) -> dict[str, str]:
    """Compile `closed_loop.c` into `results/benchmarks/build/` (shared libraries for
    ctypes; rebuilt when the source is newer); returns `{build name: library path}`.

    With `observer` (`(name, observer, T_s)`: an `AbstractObserver` of pmsmjax and the
    sampling period, s) the loop is sensorless: `pmsmjax.firmware.export_c` writes the
    observer's step in each precision and the loop is built with it (always rebuilt)."""
    BUILD.mkdir(parents=True, exist_ok=True)
    src = HERE / "closed_loop.c"
    out = {}
    for name, extra in C_BUILDS.items():
        lib = BUILD / f"closed_loop_{name}.so"
        stale = not lib.exists() or lib.stat().st_mtime < src.stat().st_mtime
        if observer is not None:
            from pmsmjax.firmware import export_c

            obs_name, obs, T_s = observer
            gen = BUILD / f"{obs_name}_{name.split('_')[0]}"
            export_c(obs, T_s, gen, float32=name.startswith("float32"))
            lib = BUILD / f"closed_loop_{obs_name}_{name}.so"
            extra = [*extra, "-DPMSM_SENSORLESS", f"-I{gen}"]
            stale = True
        cmd = ["gcc", "-O3", "-march=native", "-shared", "-fPIC", *extra, str(src), "-o",
               str(lib), "-lm"]
        if stale:
            if verbose:
                print("  $", " ".join(cmd))
            subprocess.run(cmd, check=True)
        out[name] = str(lib)
    return out


def c_simulate(lib_path: str, params: dict, w_final: np.ndarray, n_steps: int) -> np.ndarray:
    """Run `len(w_final)` drives of the C reference for `n_steps` periods; returns the
    (B, 6) final `(i_d, i_q, theta, w_m, ise_w, ok)` in the library's precision."""
    dt = np.float32 if "float32" in Path(lib_path).name else np.float64
    lib = ctypes.CDLL(lib_path)
    w = np.ascontiguousarray(w_final, dtype=dt)
    out = np.zeros((w.shape[0], 6), dt)
    lib.simulate_batch(ctypes.byref(_CParams(**params)), ctypes.c_int(w.shape[0]),
                       ctypes.c_int(n_steps), w.ctypes.data_as(ctypes.c_void_p),
                       out.ctypes.data_as(ctypes.c_void_p))
    return out
