"""Certifiable SDP rotation averaging (paper 2): conic build, solve with fallback, certificate, cvxpy reference.

- :mod:`~pipeline.averaging.sdp.conic`: the four relaxations as sparse ``(A, b, c, K)``;
- :mod:`~pipeline.averaging.sdp.solve`: :func:`solve_sdp` (SCS or Clarabel, the tight
  Clarabel fallback) and its options :class:`SdpConfig`;
- :mod:`~pipeline.averaging.sdp.certificate`: rank, rounding, costs, gap, and the resolution test a certified
  solution passes;
- :mod:`~pipeline.averaging.sdp.refine`: the Newton polish of a rounding, the dual certificate's sharper bound, and
  the start proven optimal without a conic solve (``certify_start``);
- :mod:`~pipeline.averaging.sdp.robust`: the SDP on the robust stage's edges, with the statement of what it proves;
- :mod:`~pipeline.averaging.sdp.cvxpy_ref`: the readable cvxpy statement, a slow reference.
"""

from pipeline.averaging.sdp.conic import (
    SOLVERS,
    VARIANTS,
    ConicProblem,
    build_conic,
    conv_so3_lmi,
    edge_weights,
    svec_index,
    unsvec,
)
from pipeline.averaging.sdp.solve import FALLBACK_SCS_MAX_ITERS, SdpConfig, solve_sdp

__all__ = ["VARIANTS", "SOLVERS", "ConicProblem", "SdpConfig", "solve_sdp", "build_conic", "edge_weights",
           "svec_index", "unsvec", "conv_so3_lmi", "FALLBACK_SCS_MAX_ITERS"]
