"""The motor presets: the drives of the papers pmsmjax reproduces (zhang2022, stumper,
morawiec2023, li-fa-leso) as `Drive`s, by name (`preset`, `PRESET_NAMES`). Every preset's
`Drive.notes` states the assumptions made where a paper gives no number."""

from __future__ import annotations

import dataclasses
import inspect
import math

import equinox as eqx
import numpy as np

from .._validate import check_positive
from ._magnetic import AlgebraicSaturation
from ._params import (
    BaseValues,
    Drive,
    DualThreePhaseParams,
    EMFHarmonics,
    Inverter,
    Mechanics,
    PMSMParams,
)


def _zhang750() -> Drive:
    n_p, n_rpm = 5, 2400.0
    return Drive(
        motor=PMSMParams(R_s=0.78, L_d=2.46e-3, L_q=2.68e-3, psi_f=0.056, n_p=float(n_p)),
        mechanics=Mechanics(J=1.5e-3, B=0.0),
        inverter=Inverter(u_dc=311.0),
        base=BaseValues.from_rated(311.0 / math.sqrt(2.0), 4.8, n_rpm, float(n_p)),
        w_rated=n_p * 2 * math.pi * n_rpm / 60,
        tau_rated=2.4,
        i_max=2.0 * math.sqrt(2.0) * 4.8,
        name="zhang750",
        notes=(
            "zhang2022 Table I (750 W, 2400 rpm, 2.4 N m, 4.8 A rms, 311 V dc; the table's "
            "second 'L_d' is L_q). Assumed: J = 1.5e-3 kg m^2, B = 0 (not given); rated "
            "line voltage 311/sqrt(2) = 220 V rms for the voltage base; current limit "
            "2x rated peak."
        ),
    )


def _stumper_mt5() -> Drive:
    n_p, n_rpm = 3, 3000.0
    I_peak = 6.3
    return Drive(
        motor=PMSMParams(R_s=0.86, L_d=4.8e-3, L_q=7.2e-3, psi_f=0.236, n_p=float(n_p)),
        mechanics=Mechanics(J=2.0e-3, B=0.0),
        inverter=Inverter(u_dc=400.0 * math.sqrt(2.0)),
        base=BaseValues.from_rated(400.0, I_peak / math.sqrt(2.0), n_rpm, float(n_p)),
        w_rated=n_p * 2 * math.pi * n_rpm / 60,
        tau_rated=8.8,
        i_max=I_peak,
        name="stumper_mt5",
        notes=(
            "stumper Table I (3 pole pairs, 3000 rpm, 8.8 N m, 6.3 A, L_d 4.8 mH, L_q 7.2 mH, "
            "R 0.86 Ohm, K 0.236 V s, 400 V). K read as PM flux linkage; 6.3 A read as the "
            "peak current limit (= I_b); 400 V read as rated line rms voltage (u_dc = 566 V "
            "assumed). The paper's estimator uses a single L = 7 mH. Assumed: J = 2e-3 kg m^2."
        ),
    )


#: The slot-harmonic amplitude the morawiec2023 experiments use when the slot harmonic is
#: switched on (back-EMF of each of the orders -17 and +19 relative to the fundamental).
#: The paper gives no number; its Fig. 8 shows a clearly visible but small slot ripple on
#: the measured EMF, read here as a few per cent: 3 % each (an assumption).
MORAWIEC_SLOT_HARMONIC = 0.03


def _morawiec_ipm3k5(slot_harmonic: float = 0.0, trapezoid: float = 0.0) -> Drive:
    """morawiec2023 Table I. `slot_harmonic`: back-EMF amplitude (-, relative to the
    fundamental) of each of the two slot harmonics of a 36-slot, 2-pole-pair machine,
    orders -17 and +19 (18 slots per pole pair: the phase EMF carries 18k -+ 1, which in
    rotor coordinates is the 18th-order ripple the paper calls dominant); `trapezoid`:
    amplitude of the -5/+7 pair of a flat-topped (trapezoidal) EMF. Both 0 by default (a
    sinusoidal machine, as the paper's observer model)."""
    n_p, n_rpm = 2, 1500.0
    U_b, I_b, w_b = 285.0, 12.97, 2 * math.pi * 50.0
    base = BaseValues(U_b=U_b, I_b=I_b, w_b=w_b, n_p=float(n_p))
    Z_b, L_b, psi_b = U_b / I_b, U_b / I_b / w_b, U_b / w_b
    check_positive("preset('morawiec_ipm3k5')", "slot_harmonic", slot_harmonic, "-",
                   allow_zero=True)
    check_positive("preset('morawiec_ipm3k5')", "trapezoid", trapezoid, "-",
                   allow_zero=True)
    orders, amps = [], []
    if float(trapezoid) > 0:
        # phase pi at theta = 0 for both: the 5th and 7th flatten the top of the EMF
        orders += [-5, 7]
        amps += [float(trapezoid)] * 2
    if float(slot_harmonic) > 0:
        orders += [-17, 19]
        amps += [float(slot_harmonic)] * 2
    harmonics = None
    if orders:
        phase = [math.pi if abs(h) in (5, 7) else 0.0 for h in orders]
        harmonics = EMFHarmonics(order=orders, amplitude=amps, phase=phase)
    return Drive(
        motor=PMSMParams(R_s=0.035 * Z_b, L_d=0.28 * L_b, L_q=0.82 * L_b,
                         psi_f=0.89 * psi_b, n_p=float(n_p), harmonics=harmonics),
        mechanics=Mechanics(J=0.012, B=0.0),
        inverter=Inverter(u_dc=560.0),
        base=base,
        w_rated=w_b,
        tau_rated=3500.0 / (n_rpm * 2 * math.pi / 60),
        i_max=7.5 * math.sqrt(2.0),
        name="morawiec_ipm3k5",
        notes=(
            "morawiec2023 Table I in p.u. (R_s 0.035, L_d 0.28, L_q 0.82, psi_f 0.89) with "
            "U_b = 285 V, I_b = 12.97 A as the table gives, w_b = 2 pi 50 rad/s "
            "(1500 rpm, 2 pole pairs). 36 slots: the 18th-order slot harmonic (orders "
            "-17/+19) with preset('morawiec_ipm3k5', slot_harmonic=a) (amplitude not "
            "given; off by default). Assumed: J = 0.012 kg m^2, "
            "u_dc = 560 V, current limit sqrt(2) x 7.5 A."
        ),
    )


def ipm3k5_saturation() -> AlgebraicSaturation:
    r"""The assumed saturation of the `"ipm3k5_sat"` preset: an `AlgebraicSaturation`
    (Hinkkanen et al. 2017 with a magnet current) of the morawiec2023 3.5 kW IPMSM.

    No measured map of that machine is published, so its saturation is chosen here, with
    typical values for a small interior-PM machine, and every number follows from five
    targets (solved once, the coefficients below; `tests/test_saturation.py` checks them):

    - at zero current the incremental inductances and the PM flux are Table I's
      (L_d 0.28 p.u. = 19.58 mH, L_q 0.82 p.u. = 57.35 mH, psi_f 0.89 p.u. = 0.8074 V s);
    - the magnet operates on the knee of the d-axis curve: 30 % of the d-axis inverse
      inductance at the PM flux comes from saturation (S = 4), so the d-axis incremental
      inductance rises by about 30 % as the field is weakened to -i_max;
    - the q axis saturates with its own and the d-axis flux (T = U = V = 2): the q-axis
      apparent inductance at the current limit i_max = 10.6 A on the q axis is 60 % of its
      small-current value (a 40 % drop, typical of IPMSMs at rated current);
    - cross-saturation lowers the PM flux seen by the stator at that current to 95 % of
      its no-load value.

    Even exponents make the model a polynomial in the flux, smooth everywhere (odd ones,
    as in the paper's SyRM example, leave a kink in the inductance at zero flux).
    """
    return AlgebraicSaturation(a_d0=35.74250589215756, a_dd=7.209385221958249,
                               a_q0=17.43536872788174, a_qq=0.7114285380906579,
                               a_dq=1000.0388151217833, i_f=31.331814285714287,
                               S=4.0, T=2.0, U=2.0, V=2.0)


def _ipm3k5_sat() -> Drive:
    """The morawiec2023 3.5 kW IPMSM with the saturation of `ipm3k5_saturation`, sampled
    into a flux map as a finite-element tool would deliver it (1 A class spacing over
    -2..0.5 i_max in d and -2..2 i_max in q), and the small-current constants of Table I
    as the model its controllers and observers deploy."""
    drive = _morawiec_ipm3k5()
    i_max = float(drive.i_max)
    flux_map = ipm3k5_saturation().sample(np.linspace(-2.0 * i_max, 0.5 * i_max, 26),
                                          np.linspace(-2.0 * i_max, 2.0 * i_max, 41))
    motor = eqx.tree_at(lambda m: m.magnetic, drive.motor, flux_map,
                        is_leaf=lambda x: x is None)
    return dataclasses.replace(drive, motor=motor, name="ipm3k5_sat", notes=(
        drive.notes + " Saturated (assumed, not measured): the algebraic saturation "
        "model of Hinkkanen et al. (2017) with a magnet current, chosen so that the "
        "small-current inductances and PM flux are Table I's, the q-axis apparent "
        "inductance falls 40 % and the PM flux 5 % at i_max on the q axis, and the d "
        "axis sits on its knee (pmsmjax.ipm3k5_saturation), sampled into a "
        "26 x 41 flux map over i_d -21.2..5.3 A, i_q -21.2..21.2 A. The constants "
        "L_d, L_q, psi_f are the small-current ones the drive deploys."))


def _li_dtp() -> Drive:
    n_p, n_rpm = 5, 600.0
    I_peak = 8.0
    ab = PMSMParams(R_s=0.5, L_d=6e-3, L_q=10e-3, psi_f=0.2, n_p=float(n_p),
                    harmonics=EMFHarmonics(order=(-5, 7), amplitude=(0.03, 0.02)))
    w_rated = n_p * 2 * math.pi * n_rpm / 60
    return Drive(
        motor=DualThreePhaseParams(ab=ab, L_xy=1.0e-3, gamma=math.pi / 6),
        mechanics=Mechanics(J=0.02, B=0.0),
        inverter=Inverter(u_dc=300.0),
        base=BaseValues(U_b=300.0 / math.sqrt(3.0), I_b=I_peak, w_b=w_rated, n_p=float(n_p)),
        w_rated=w_rated,
        tau_rated=3.0 * n_p * 0.2 * I_peak,
        i_max=I_peak,
        name="li_dtp",
        notes=(
            "li-fa-leso gives no machine table; everything here is assumed: "
            "dual three-phase IPMSM, 5 pole pairs, 600 rpm = 50 Hz, "
            "R_s 0.5 Ohm, L_d 6 mH, L_q 10 mH, psi_f 0.2 V s per set, 30 deg shifted sets, "
            "8 A peak rated current, back-EMF 5th (3 %) and 7th (2 %) harmonics, "
            "L_xy = 1 mH, J = 0.02 kg m^2, u_dc = 300 V, rated torque 3 n_p psi_f I."
        ),
    )


_PRESETS = {
    "zhang750": _zhang750,
    "stumper_mt5": _stumper_mt5,
    "morawiec_ipm3k5": _morawiec_ipm3k5,
    "li_dtp": _li_dtp,
    "ipm3k5_sat": _ipm3k5_sat,
}

PRESET_NAMES = tuple(_PRESETS)


def preset(name: str, **options) -> Drive:
    """One of the motor presets (`PRESET_NAMES`) as a `Drive`.

    `options`: keyword options of the preset, where it has any:
    `"morawiec_ipm3k5"` takes `slot_harmonic` and `trapezoid` (back-EMF harmonic
    amplitudes relative to the fundamental, default 0).

    - `"zhang750"`: zhang2022 Table I, 750 W PMSM.
    - `"stumper_mt5"`: stumper Table I, MT5 IPMSM.
    - `"morawiec_ipm3k5"`: morawiec2023 Table I, 3.5 kW IPMSM.
    - `"li_dtp"`: assumed dual three-phase IPMSM for li-fa-leso.
    - `"ipm3k5_sat"`: the 3.5 kW IPMSM with an assumed saturation (a flux map).

    `Drive.notes` states every assumption made.
    """
    try:
        factory = _PRESETS[name]
    except KeyError:
        raise ValueError(
            f"Unknown motor preset {name!r}; choose one of {', '.join(PRESET_NAMES)}."
        ) from None
    if options:
        allowed = [k for k in inspect.signature(factory).parameters]
        bad = sorted(set(options) - set(allowed))
        if bad:
            raise ValueError(
                f"`preset({name!r}, ...)`: unknown option(s) {', '.join(bad)}; "
                f"{'it has ' + ', '.join(allowed) if allowed else 'it has no options'}.")
    return factory(**options)
