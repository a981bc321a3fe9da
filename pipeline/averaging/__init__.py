"""Rotation averaging: robust IRLS (paper 1), IRLS in the H metric, ℓ1, Weiszfeld, SDP-cSO(3) (paper 2).

Layout:

- :mod:`~pipeline.averaging.kernel`: residuals, update, Laplacian solver, graph checks;
- :mod:`~pipeline.averaging.losses`, :mod:`~pipeline.averaging.init`: the losses of
  paper 1, Table 1, and spanning-tree starts;
- the methods, each a module with a typed config and a solve function:
  :mod:`~pipeline.averaging.irls`, :mod:`~pipeline.averaging.irls_h`,
  :mod:`~pipeline.averaging.l1`, :mod:`~pipeline.averaging.weiszfeld`,
  :mod:`~pipeline.averaging.sdp`;
- :mod:`~pipeline.averaging.registry`: THE method registry (names, tokens, options,
  defaults) and :func:`register` to add a method;
- :func:`average` (:mod:`~pipeline.averaging.solve`): any registered method on the
  largest connected component;
- :mod:`~pipeline.averaging.stage`: the stage (outputs, record, verification),
  :mod:`~pipeline.averaging.cli`: ``python -m pipeline.average``;
- :mod:`~pipeline.averaging.convergence`: error against time (paper 1, Fig. 5c);
- :mod:`~pipeline.averaging.peers`: pycolmap and GTSAM, measured in the benchmarks.
"""

from pipeline.averaging.registry import Method, MethodSpec, get_method, parse_method, parse_methods, register, unregister
from pipeline.averaging.result import AveragingResult
from pipeline.averaging.solve import average

__all__ = ["AveragingResult", "average", "Method", "MethodSpec", "register", "unregister", "get_method",
           "parse_method", "parse_methods"]
