"""`pmsmjax feasibility`: feasibility maps of any observer over two of its design
parameters (zhang2022 Fig. 1 for the ESO's (zeta1, w1/|w0|)): the per-design body of
`pmsmjax.analysis.design_map` (or of `feasibility_map` for the zhang2022 shorthand), run
point by point by `pmsmjax.analysis.run_sweep` (chunked, resumable, sharded over every
device and, with `jax.distributed`, over several processes or hosts)."""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np

from .._files import json_safe, json_text, save_npz
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, motor_text
from ._observer_options import MODEL_PARAMETERS, add_observer_options, observer_from_args
from ._operating_point import (
    add_operating_point_options,
    current_from_args,
    saturated_operating_point_from_args,
)
from ._output import add_output_options, first_line, prepare_out_dir
from ._sweep_options import (
    add_sweep_options,
    init_distributed,
    is_writer,
    run_sweep_with,
    sweep_settings,
)
from ._values import CLIError, grid, grid_values, named_grid


#: `status` codes of the map (those of `pmsmjax.analysis.DesignClass`).
STATUS = {0: "feasible", 1: "infeasible", 2: "no equilibrium", -1: "degenerate"}
STATUS_CODES = "0 feasible, 1 infeasible, 2 no equilibrium, -1 degenerate or failed"
_DEFAULT_AXES = (("zeta1", (0.0, 5.0, 101)), ("ratio", (0.0, 2.0, 101)))


def _feasibility_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_operating_point_options(p, speed="list")
    add_observer_options(p, default="eso", mismatch=True, flux="grid", fixed_at=False,
                         default_note=": zhang2022's nonlinear ESO, the default of "
                                      "every command; any registered observer")
    g = p.add_argument_group("design axes")
    g.add_argument("--x", type=named_grid, default=None, metavar="NAME=LO:HI:N",
                   help="first axis of the map: a design parameter of the observer (a name "
                        "of --gain; SI units as there) and N values from LO to HI "
                        "inclusive, e.g. --x w2=100:600:26; give --y too")
    g.add_argument("--y", type=named_grid, default=None, metavar="NAME=LO:HI:N",
                   help="second axis, e.g. --y zeta2=0.5:2:16")
    g.add_argument("--zeta1", type=grid(nonneg=True), default=None, metavar="LO:HI:N",
                   help="zhang2022 shorthand for --x zeta1=LO:HI:N: damping ratios of the "
                        "flux poles (-, >= 0), N points from LO to HI inclusive, or a single "
                        "number (default with --ratio, and when neither --x nor --y is "
                        "given: 0:5:101, zhang2022 Fig. 1)")
    g.add_argument("--ratio", type=grid(nonneg=True), default=None, metavar="LO:HI:N",
                   help="zhang2022 shorthand for --y ratio=LO:HI:N: w1 / |w0| (-, >= 0; 0 is "
                        "degenerate), or a single number (default 0:2:101, zhang2022 Fig. 1)")
    add_output_options(p, "results")
    add_sweep_options(p)


def _axes(args, choice) -> tuple[tuple[str, np.ndarray], tuple[str, np.ndarray]]:
    eso = args.zeta1 is not None or args.ratio is not None
    generic = args.x is not None or args.y is not None
    if eso and generic:
        raise CLIError("--zeta1/--ratio and --x/--y both give the axes of the map; allowed: "
                       "one of the two spellings (--zeta1 A:B:N is --x zeta1=A:B:N, --ratio "
                       "is --y ratio=...)")
    units = choice.cls.design_units
    allowed = ", ".join(units) or "none"
    if generic:
        if args.x is None or args.y is None:
            raise CLIError(f"{'--x' if args.y is None else '--y'} needs "
                           f"{'--y' if args.y is None else '--x'} as well (two design "
                           f"parameters of the {choice.name} observer: {allowed})")
        axes = (args.x, args.y)
        opts = ("--x", "--y")
    else:
        axes = ((name, spec if given is None else given) for (name, spec), given in
                zip(_DEFAULT_AXES, (args.zeta1, args.ratio)))
        axes = tuple(axes)
        opts = ("--zeta1", "--ratio")
    for opt, (name, spec) in zip(opts, axes):
        if name not in units:
            what = f"{opt} {name}={spec[0]:g}:{spec[1]:g}:{spec[2]}" if opt in ("--x", "--y") \
                else opt
            hint = "" if generic else "; choose the axes with --x NAME=LO:HI:N --y NAME=LO:HI:N"
            raise CLIError(f"{what}: the {choice.name} observer has no design parameter "
                           f"{name!r}; allowed: {allowed}{hint}")
    if axes[0][0] == axes[1][0]:
        raise CLIError(f"--x {axes[0][0]}=... and --y {axes[1][0]}=...: the two axes must be "
                       f"different design parameters; allowed: two of {allowed}")
    gains = choice.gains
    for opt, (name, _) in zip(opts, axes):
        if name in gains:
            raise CLIError(f"{opt} {name}=... and a fixed value of {name} (--gain or a "
                           f"shorthand) both set {name}; give it once")
    return tuple((name, grid_values(spec)) for name, spec in axes)


def _plot(fm, title: str, path: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 5.0))
    ax = fig.add_subplot()
    if (fm.x_name, fm.y_name) == ("zeta1", "ratio"):
        from pmsmjax.plotting import plot_feasibility

        plot_feasibility(fm, ax=ax)
    else:
        _plot_generic(fm, ax)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=120)


def _plot_generic(fm, ax) -> None:
    """Infeasible regions over any two design parameters, one colour per speed."""
    from matplotlib.patches import Patch

    colours = ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown")
    x, y = np.asarray(fm.x), np.asarray(fm.y)
    X, Y = np.meshgrid(x, y, indexing="ij")
    st = np.asarray(fm.status)[:, 0]
    handles = []
    for i, s in enumerate(np.asarray(fm.speeds)):
        col = colours[i % len(colours)]
        inf = (st[i] == 1).astype(float)
        if inf.any():
            ax.contourf(X, Y, inf, levels=[0.5, 1.5], colors=[col], alpha=0.25)
            ax.contour(X, Y, inf, levels=[0.5], colors=[col], linewidths=1.8)
        handles.append(Patch(facecolor=col, alpha=0.4, edgecolor=col,
                             label=f"w0 = {s:g} p.u.: infeasible {inf.mean():.1%}"))
    for code, hatch, label in ((-1, "////", "degenerate"), (2, "..", "no equilibrium")):
        mask = np.any(st == code, axis=0).astype(float)
        if mask.any():
            ax.contourf(X, Y, mask, levels=[0.5, 1.5], colors="none", hatches=[hatch])
            handles.append(Patch(facecolor="none", hatch=hatch, edgecolor="grey", label=label))
    ax.set_xlabel(fm.x_name)
    ax.set_ylabel(fm.y_name)
    ax.legend(handles=handles, loc="best", fontsize=8)
    ax.set_title(f"{fm.observer}: feasible designs [{fm.method}]", fontsize=10)


def _zhang_shorthand(choice, xn: str, yn: str) -> dict | None:
    """The arguments of `feasibility_map` (the zhang2022 shorthand: the closed form
    zhang2022 (34)-(36) when matched, the ESO-specific general route otherwise) when it
    computes exactly this map, else None. It covers the ESO/LESO over (zeta1, ratio) with
    the minimum-norm gains zhang2022 (25), and accepts the degenerate zeta1 = 0, ratio = 0
    of zhang2022 Fig. 1."""
    from pmsmjax.observers import ESODesign, ESOObserver, LESOObserver

    obs = choice.observer
    if (xn, yn) != ("zeta1", "ratio") or type(obs) not in (ESOObserver, LESOObserver):
        return None
    d = obs.design
    if not isinstance(d, ESODesign) or float(d.n2) != 0.0 or float(d.n3) != 0.0:
        return None
    kw = dict(zeta2=float(d.zeta2), w2=float(d.w2),
              motor_hat=obs.motor if choice.mismatched else None)
    if isinstance(obs, ESOObserver):
        kw.update(a=float(obs.a), eta=float(obs.eta))
    return kw


def _point_fn(choice, drive, x, y, i_pu):
    """`(fn, method)`: the classification of one point `{"w_m": rad/s, "x", "y"}` of the
    map, and the method's name. The same kernels as the in-memory maps: the zhang2022
    shorthand (`feasibility_map`'s, through `classify_designs`: the closed form zhang2022
    (34)-(36) when matched, the ESO-specific general route otherwise) when it computes
    exactly this map, else `design_map`'s body. Every zhang2022 design is degenerate at
    standstill (w1 = ratio |w0| = 0): status -1 there and nothing else, as before."""
    import jax.numpy as jnp

    from pmsmjax.analysis import DesignClass, classify_designs
    from pmsmjax.analysis._feasibility import (
        _design_map_setup,
        _design_point,
        _resolve_method,
    )

    i_si = jnp.asarray(np.asarray(i_pu, float) * float(drive.base.I_b))  # A
    kw = _zhang_shorthand(choice, x[0], y[0])
    if kw is None:
        # (plant only with mismatch: `design_map(plant=None)` allows the closed form)
        plant = choice.plant if choice.mismatched else None
        speeds_probe = np.asarray([1.0])  # the method does not depend on the speed
        obs, plant_in, method = _design_map_setup(
            choice.observer, drive, speeds_probe, x, y, np.asarray([i_pu], float), plant,
            "auto", jnp.float64)

        def fn(p):
            return _design_point(obs, plant_in, p["w_m"], i_si, p["x"], p["y"], x[0], y[0],
                                 method, {})

        return fn, method
    motor = drive.three_phase_motor
    method = _resolve_method("feasibility_map", "auto", kw["motor_hat"], kw.get("a", 1.0))

    def fn(p):
        w0 = p["w_m"]
        res = classify_designs(motor, w0, i_si, p["x"], p["y"], method=method, **kw)
        still = w0 == 0
        nan = jnp.full_like(res.stable_theta, jnp.nan)
        return DesignClass(
            status=jnp.where(still, -1, res.status).astype(jnp.int32),
            n_nonzero=jnp.where(still, 0, res.n_nonzero),
            stable_theta=jnp.where(still, nan, res.stable_theta),
            theta=jnp.where(still, jnp.nan, res.theta),
            stable=res.stable & ~still,
            principal_stable=res.principal_stable & ~still,
            principal_theta=jnp.where(still, nan, res.principal_theta))

    return fn, method


#: Per-point functions of earlier maps in this process, by everything they close over
#: (`_point_key`): a map computed again in the same process (a resumed or repeated
#: command, a notebook, the tests) hands `run_sweep` the same function object, so its
#: compiled chunk function is reused instead of compiled again.
_POINT_FNS: dict[str, tuple] = {}


def _point_key(choice, drive, x_name, y_name, i_pu) -> str:
    """A hash of what the per-point function closes over: the observer (design and
    model), the plant, the drive's machine and bases, the axes' names and the current."""
    import hashlib

    leaves, treedef = jax.tree_util.tree_flatten(
        (choice.observer, choice.plant, drive.three_phase_motor))
    h = hashlib.sha256(repr((str(treedef), x_name, y_name, tuple(map(float, i_pu)),
                             float(drive.w_rated), float(drive.base.I_b))).encode())
    for leaf in leaves:
        a = np.asarray(leaf)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes() if a.dtype.kind != "O" else repr(leaf).encode())
    return h.hexdigest()


def _map(choice, drive, speeds, x, y, i_pu, settings):
    """The `FeasibilityMap` over `speeds` (p.u.), evaluated point by point by `run_sweep`
    (chunked, resumable, sharded over every device of every process); `(map, chunk
    infos)`. Only process 0 writes the sweep's files. The map holds what the command
    writes: its `theta_deg` and `stable` (every non-designed equilibrium) are empty (last
    axis of length 0), so that the sweep neither computes, holds nor stores them."""
    import jax.numpy as jnp

    from pmsmjax.analysis import FeasibilityMap, grid_product

    key = _point_key(choice, drive, x[0], y[0], i_pu)
    if key not in _POINT_FNS:
        fn, method = _point_fn(choice, drive, x, y, i_pu)

        def point(p):
            # what the command writes, in its units and types (the angles in degrees,
            # the status codes -1..2 as int8, the counts of non-principal equilibria as
            # int8 where their slots, `theta`'s, fit): the sweep holds and stores no more
            res = fn(p)
            count = jnp.int8 if res.theta.shape[-1] < 127 else jnp.int32
            return {"design_status": res.status.astype(jnp.int8),
                    "n_nonzero": res.n_nonzero.astype(count),
                    "stable_theta_deg": jnp.degrees(res.stable_theta),
                    "principal_stable": res.principal_stable,
                    "principal_theta_deg": jnp.degrees(res.principal_theta)}

        if len(_POINT_FNS) >= 16:
            _POINT_FNS.clear()
        _POINT_FNS[key] = point, method
    point, method = _POINT_FNS[key]
    if all(s == 0.0 for s in speeds) and _zhang_shorthand(choice, x[0], y[0]) is not None:
        method = "none (standstill only)"
    w_r = float(drive.w_rated)

    # points in the order of the command's file, (speed, y, x): its arrays are then the
    # sweep's outputs as they are, without a transposed copy
    grid = grid_product(w_m=np.asarray(speeds, float) * w_r, y=y[1], x=x[1])
    metadata = json_safe({
        "command": "pmsmjax feasibility", "motor": drive.name, "w_rated": w_r,
        "I_b": float(drive.base.I_b), "i_dq_pu": list(i_pu), "x_name": x[0],
        "y_name": y[0], "method": method, "observer": choice.info()})
    infos = []
    # the command's feasibility.npz holds the map: a finished sweep keeps its manifest
    # alone (writing the map twice cost more than computing it), an interrupted one its
    # chunk files to resume from
    out = run_sweep_with(settings, point, grid, metadata=metadata,
                         on_chunk_done=infos.append, keep_result=False)
    per = {k: v[:, None].swapaxes(2, 3) for k, v in out.items()}  # (speed, load = 1, x, y)
    none = np.zeros((*per["design_status"].shape, 0))  # the equilibria are not kept
    fm = FeasibilityMap(
        status=per["design_status"], n_nonzero=per["n_nonzero"],
        stable_theta_deg=per["stable_theta_deg"], theta_deg=none,
        stable=none.astype(bool), principal_stable=per["principal_stable"],
        principal_theta_deg=per["principal_theta_deg"], speeds=np.asarray(speeds, float),
        i_dq=np.asarray([i_pu], float), x=x[1], y=y[1], w_rated=w_r,
        I_b=float(drive.base.I_b), method=method, frame="observer", x_name=x[0],
        y_name=y[0], observer=type(choice.observer).__name__)
    return fm, infos


def feasibility_command(args: argparse.Namespace) -> int:
    settings = init_distributed(sweep_settings(args))  # before any JAX computation
    drive = drive_from_args(args)
    choice = observer_from_args(args, drive, skip=("zeta1", "ratio"))
    (xn, x), (yn, y) = _axes(args, choice)
    speeds = [s for group in (args.speed or [[0.5]]) for s in group]
    # a saturated motor: the mismatch from the map at the first speed's operating point
    choice, saturated = saturated_operating_point_from_args(args, drive, choice, speeds[0])
    i_pu, _ = current_from_args(args, drive)
    writer = is_writer()
    out = prepare_out_dir(args.out) if writer else args.out
    S, NX, NY = len(speeds), len(x), len(y)
    if writer:
        print(first_line("feasibility", motor_text(drive, args), choice.describe(),
                         f"i_dq = ({i_pu[0]:g}, {i_pu[1]:g}) p.u.",
                         f"{NX} x {NY} designs ({xn} x {yn}) at {S} "
                         f"speed{'s' if S > 1 else ''}"), flush=True)
        if saturated:
            print(saturated + (f" (at the first speed, {speeds[0]:g} p.u.)" if S > 1 else ""),
                  flush=True)
    t0 = time.perf_counter()
    try:
        fm, infos = _map(choice, drive, speeds, (xn, x), (yn, y), i_pu, settings)
    except ValueError as e:
        raise CLIError(f"{choice.describe()}: {e}") from None
    status = np.asarray(fm.status)
    t_map = time.perf_counter() - t0
    n_loaded = sum(i.loaded for i in infos)
    size = max(i.stop - i.start for i in infos)
    sweep_line = (f"sweep: {len(infos)} chunk{'s' if len(infos) > 1 else ''} of up to "
                  f"{size} points on {jax.device_count()} device"
                  f"{'s' if jax.device_count() > 1 else ''} in {jax.process_count()} "
                  f"process{'es' if jax.process_count() > 1 else ''}"
                  + (f", {n_loaded} reused from an earlier run" if n_loaded else "")
                  + f"; files in {settings.sweep_dir}")
    if not writer:
        print(f"pmsmjax feasibility: process {jax.process_index()} of "
              f"{jax.process_count()} done ({sweep_line}); process 0 writes the outputs")
        return 0

    # FeasibilityMap arrays are (speed, load, x, y); the file's are (speed, y, x), so that
    # rows follow y (zhang2022 Fig. 1: ratio vertical, zeta1 horizontal)
    per_design = {
        "status": status[:, 0].transpose(0, 2, 1).astype(np.int8, copy=False),
        "n_nonzero": np.asarray(fm.n_nonzero)[:, 0].transpose(0, 2, 1),
        "stable_theta_deg": np.asarray(fm.stable_theta_deg)[:, 0].transpose(0, 2, 1),
        "principal_stable": np.asarray(fm.principal_stable)[:, 0].transpose(0, 2, 1),
        "principal_theta_deg": np.asarray(fm.principal_theta_deg)[:, 0].transpose(0, 2, 1),
    }
    one = S == 1
    if one:
        per_design = {k: v[0] for k, v in per_design.items()}
    info = choice.info()
    inputs = {
        "x_name": np.str_(xn), "y_name": np.str_(yn), "x": x, "y": y,
        "speed": np.asarray(speeds[0] if one else speeds, float),
        "i_dq": np.asarray(i_pu, float), "w_rated": np.float64(fm.w_rated),
        "I_b": np.float64(fm.I_b), "motor": np.str_(drive.name),
        "observer": np.str_(choice.name), "observer_class": np.str_(choice.cls.__name__),
        "method": np.str_(fm.method), "status_codes": np.str_(STATUS_CODES),
        "design": np.str_(json_text(info["design"])),
        "observer_model": np.str_(json_text(info["model"])),
    }
    m = choice.observer.motor
    for p in MODEL_PARAMETERS:
        inputs[f"mismatch_{p}"] = np.float64(float(getattr(m, p)) /
                                             float(getattr(choice.plant, p)))
    inputs[xn], inputs[yn] = x, y  # e.g. zeta1, ratio
    for k, v in choice.observer.design_parameters().items():
        if k not in inputs and k not in per_design and np.ndim(v) == 0:
            inputs[k] = np.float64(v)  # the fixed design parameters, e.g. zeta2, w2
    files = {"data": os.path.join(out, "feasibility.npz")}
    save_npz(files["data"], {**per_design, **inputs})

    plot_note = ""
    if not args.no_plot:
        if NX < 2 or NY < 2:
            plot_note = f"no PNG: the map needs at least 2 values of {xn} and of {yn}"
        else:
            files["plot"] = os.path.join(out, "feasibility.png")
            title = f"{drive.name}, {choice.describe()}"
            _plot(fm, title, files["plot"])

    print(f"classified {S * NX * NY} designs in {t_map:.2f} s ({fm.method})")
    print(sweep_line)
    for i, s in enumerate(speeds):
        st = status[i, 0]
        counts = {c: int(np.count_nonzero(st == c)) for c in (0, 1, 2, -1)}
        line = f"speed {s:g} p.u.: " + ", ".join(f"{STATUS[c]} {n}" for c, n in counts.items())
        if counts[1]:  # the static errors: finite exactly at the infeasible designs
            th = np.asarray(fm.stable_theta_deg)[i, 0]
            line += (f"; static error of infeasible designs {np.nanmin(th):.3g}.."
                     f"{np.nanmax(th):.3g} deg")
        if s == 0.0:
            line += " (standstill)"
        print(line)
    if plot_note:
        print(plot_note)
    print(f"wrote {', '.join(files.values())}")
    return 0


COMMAND = Command(
    name="feasibility",
    help="feasibility map of any observer over two design parameters (zhang2022 Fig. 1)",
    description=(
        "Classify every design of a grid over two design parameters of the observer (--x "
        "NAME=LO:HI:N --y NAME=LO:HI:N; for the zhang2022 observers --zeta1 and --ratio = "
        "w1/|w0|, the axes of zhang2022 Fig. 1, are the default) at one or more speeds: "
        "feasible when no equilibrium of the error dynamics other than the designed one is "
        "stable (pmsmjax.analysis.design_map: the closed form zhang2022 (34)-(36) for the "
        "matched ESO/LESO, the generic equilibria route otherwise, e.g. with observer-model "
        "mismatch). Writes DIR/feasibility.npz (no pickled objects) with x (NX,), y (NY,), "
        "x_name, y_name (also the axes under their names, e.g. zeta1, ratio), status (NY, "
        "NX) int8 (0 feasible, 1 infeasible, 2 no equilibrium, -1 degenerate or failed), "
        "n_nonzero (number of equilibria other than the designed one; int8 where it fits, "
        "else int32), "
        "stable_theta_deg "
        "(angle of the stable non-designed equilibrium closest to 0, deg; NaN if none), "
        "principal_stable, principal_theta_deg (NY, NX), and the inputs: speed (p.u.), i_dq "
        "(p.u.), observer, observer_class, the other design parameters (e.g. zeta2, w2), "
        "design and observer_model (JSON text), mismatch_R_s, mismatch_L_d, mismatch_L_q, "
        "mismatch_psi_f (observer / plant), w_rated (rad/s), I_b (A), motor, method, "
        "status_codes. With several speeds every per-design array gets a leading speed "
        "axis (S, NY, NX) and speed has shape (S,). DIR/feasibility.png overlays the maps "
        "of all speeds. The speeds x designs are evaluated in chunks by "
        "pmsmjax.analysis.run_sweep, sharded over every device: each finished chunk is "
        "written to --sweep-dir (default DIR/sweep, also the manifest sweep.json), and the "
        "same command run again after an interruption resumes from there; a finished "
        "sweep keeps its manifest alone (feasibility.npz holds the map). With "
        "--coordinator the same command started in several processes or on several hosts "
        "(jax.distributed) shares the work; process 0 writes the outputs."
    ),
    add_arguments=_feasibility_arguments,
    run=feasibility_command,
)
