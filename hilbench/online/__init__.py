"""The closed loop: the online identifier and the compensators (paper 000 OIIR, 004 inverse models).

* :mod:`hilbench.online.rls`: recursive least squares, one numba step kernel over explicit state
  (block and step mode), directional forgetting, symmetric covariance update, guards.
* :mod:`hilbench.online.oiir`: paper 000's identifier, FPMPI front end + OIIR weights by RLS.
"""

from hilbench.online.oiir import (
    OIIR,
    FPMPIFrontEnd,
    offline_hammerstein,
    persistence,
    re_n2_pct,
    re_ninf_pct,
)
from hilbench.online.rls import RLS

__all__ = ["RLS", "OIIR", "FPMPIFrontEnd", "re_n2_pct", "re_ninf_pct", "persistence", "offline_hammerstein"]
