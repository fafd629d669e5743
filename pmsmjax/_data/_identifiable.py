"""The parameters `pmsmjax.identify` can fit (a module of its own: the command line's
parser lists them without importing the identification and its solvers)."""

#: Parameters `identify` can fit, with their units and what excites them.
IDENTIFIABLE = {
    "R_s": ("Ohm", "current at low speed, where R_s i is not small against the back-EMF"),
    "L_d": ("H", "changes of the d-axis current (i_d steps or a varying i_d)"),
    "L_q": ("H", "changes of the q-axis current (torque steps)"),
    "psi_f": ("V s", "rotor speed (the back-EMF)"),
    "J": ("kg m^2", "speed changes under known torque (accelerations)"),
    "B": ("N m s/rad", "a range of speeds held long enough for friction to show"),
    "u_dt": ("V", "commanded voltages with changes of the current amplitude or zero "
                  "crossings of the phase currents"),
}
