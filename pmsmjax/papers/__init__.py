"""Reproductions of published experiments, one module per paper.

Each module rebuilds one paper's experiments (scenarios, settings, published numbers) with
the public API only, so that tests, notebooks and the command line share one definition of
each figure: `zhang2022` (M. Zhang, B. Xia, J. Zhang, IEEE Trans. Energy Convers. 37(4),
2022). Modules for `stumper`, `morawiec2023` and `li` will follow.
"""

from . import zhang2022 as zhang2022
from . import li as li  # noqa: E402
