"""`pmsmjax compare`: the observer comparison of the `tuning` package (`python -m tuning
compare`)."""

from ._tuning import handover_command


COMMAND = handover_command(
    "compare", "every observer, paper design and tuned, on one common grid "
               "(python -m tuning compare)",
    "Which observer for my drive? Runs every registered observer that applies to the "
    "motor on one common grid of closed-loop sensorless runs and writes one table, the "
    "numbers and figures. The same as `python -m tuning compare`.")
