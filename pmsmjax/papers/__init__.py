"""Reproductions of published experiments, one module per paper.

Each module rebuilds one paper's experiments (scenarios, settings, published numbers) with
the public API only, so that tests, notebooks and the command line share one definition of
each figure: `zhang2022` (M. Zhang, B. Xia, J. Zhang, IEEE Trans. Energy Convers. 37(4),
2022), `stumper` (J.-F. Stumper, D. Paulus, R. Kennel: the inverse parallel-model
estimator), `morawiec2023` (M. Morawiec, A. Lewicki, I. C. Odeh, 2023: the rotor-flux-vector
observer for IPMSMs) and `li` (Y. Li, Y. Hu, X. Ma, L. Liu: the back-EMF LESOs on a dual
three-phase IPMSM). The
documentation's papers page gives the full references.
"""

from . import (
    li as li,
    morawiec2023 as morawiec2023,
    stumper as stumper,
    zhang2022 as zhang2022,
)
