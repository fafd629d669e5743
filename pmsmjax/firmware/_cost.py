"""What the generated step costs on a motor-control microcontroller, measured: per
observer, one float32 step on a Cortex-M4F (`benchmarks/throughput/firmware_target.py`:
arm-none-eabi-gcc 12.2 -O2, fpv4-sp-d16 hard float, newlib's libm, run under QEMU; the
observer's default design on its paper's drive at T_s = 125 us, the largest of 64 steps
of a closed-loop recording; instructions counted, cycles estimated from the Cortex-M4's
instruction timings with no wait states). `cost_lines` turns them into the lines the
header comment and `pmsmjax export-c` print: the share of the sampling period on a
`CLOCK_HZ` part, and whether the step fits in it."""

from __future__ import annotations


#: The clock of the typical motor-control part the budget is given for (Hz).
CLOCK_HZ = 170e6

#: name: (instructions, estimated cycles) of one float32 step on a Cortex-M4F.
M4F_FLOAT32 = {
    "eso": (616, 1209), "leso": (595, 1174), "afo": (1018, 2090),
    "parallel-model": (1182, 2193), "rotor-flux": (1540, 2843),
    "c-leso": (1310, 2098), "gi-leso": (2060, 3372), "fa-leso": (1343, 2145),
    "reduced-order": (564, 1044), "nonlinear-flux": (606, 1119),
}


def cost_lines(name: str, T_s: float, float32: bool) -> tuple[str, ...]:
    """The measured cost of observer `name`'s step at sampling period `T_s` (s) as text
    lines (none for an observer not measured)."""
    if name not in M4F_FLOAT32:
        return ()
    insns, cycles = M4F_FLOAT32[name]
    share = cycles / (CLOCK_HZ * T_s)
    verdict = ("fits" if share <= 1.0 else
               "does NOT fit: the step takes longer than the sampling period")
    lines = (f"Cost: a float32 step on a Cortex-M4F takes about {cycles:,} cycles "
             f"({insns:,} instructions),",
             f"{100 * share:.0f} % of T_s at {CLOCK_HZ / 1e6:.0f} MHz -- {verdict} "
             f"(measured for the default design",
             "on the paper's drive at T_s = 125 us: benchmarks/throughput/firmware_target.py).")
    if not float32:
        lines += ("This double build needs a double-precision FPU (e.g. a Cortex-M7 with "
                  "fpv5-d16);",
                  "on a single-precision FPU its arithmetic runs in software: use --float32.")
    return lines
