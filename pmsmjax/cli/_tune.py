"""`pmsmjax tune`: the gain tuner of the `tuning` package (`python -m tuning`)."""

from ._tuning import handover_command


COMMAND = handover_command(
    "tune", "tune an observer's gains under model mismatch (the main job; python -m tuning)",
    "Gradient-based tuning of a sensorless observer's design so that it stays fast, "
    "accurate and stable when its machine model is wrong, validated on closed-loop runs "
    "it never trained on; writes the tuned gains as a table for firmware (gains.json, "
    "gains.csv, gains.h) with the tuner's verdict. The same as `python -m tuning`.")
