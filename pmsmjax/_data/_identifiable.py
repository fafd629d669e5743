"""The parameters `pmsmjax.identify` can fit (a module of its own: the command line's
parser lists them without importing the identification and its solvers)."""

#: Parameters `identify` can fit, with their units and what excites them. The last six
#: are the coefficients of an `AlgebraicSaturation` (the plant's magnetic model, with
#: the exponents held), fitted together as `"saturation"` (`SATURATION_FIT`).
IDENTIFIABLE = {
    "R_s": ("Ohm", "current at low speed, where R_s i is not small against the back-EMF"),
    "L_d": ("H", "changes of the d-axis current (i_d steps or a varying i_d)"),
    "L_q": ("H", "changes of the q-axis current (torque steps)"),
    "psi_f": ("V s", "rotor speed (the back-EMF)"),
    "J": ("kg m^2", "speed changes under known torque (accelerations)"),
    "B": ("N m s/rad", "a range of speeds held long enough for friction to show"),
    "u_dt": ("V", "commanded voltages with changes of the current amplitude or zero "
                  "crossings of the phase currents"),
    "i_dt": ("A", "commanded voltages with phase currents passing slowly through zero, "
                  "within a few i_dt of it for several samples (low speed, small or "
                  "reversing currents); currents that stay far from zero relative to i_dt "
                  "cannot show the dead time's transition"),
    "a_d0": ("1/H", "i_d steps near zero current and the back-EMF at speed"),
    "a_dd": ("A/(V s)^(S+1)", "i_d steps over the field-weakening range (down to -i_max) "
                              "at speed"),
    "a_q0": ("1/H", "i_q steps near zero current"),
    "a_qq": ("A/(V s)^(T+1)", "i_q steps up to the current limit at speed"),
    "a_dq": ("A/(V s)^(U+V+3)", "large i_q at speed (cross-saturation lowers the PM flux), "
                                "at several i_d"),
    "i_f": ("A", "rotor speed (the back-EMF) at zero d-axis current"),
}

#: The `AlgebraicSaturation` coefficients `"saturation"` stands for in `fit`.
SATURATION_FIT = ("a_d0", "a_dd", "a_q0", "a_qq", "a_dq", "i_f")
