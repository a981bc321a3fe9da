"""Refinement of averaged rotations with pycolmap's multi-view machinery, and its stage.

- :mod:`.tracks`: multi-view tracks from our inlier matches, the edge filter (numpy);
- :mod:`.model`: the in-memory COLMAP database and the starting reconstruction;
- :mod:`.mapper`: global positioning, bundle adjustment, retriangulation (pycolmap);
- :mod:`.covariance`: per-camera rotation covariance from pycolmap's BA covariance;
- :mod:`.refine`: :func:`refine_rotations` and :class:`RefineConfig`;
- :mod:`.stage`: :class:`RefineStage` (``OUT/sparse/``, ``OUT/rotations/<method>+refine.txt``)
  and ``python -m pipeline.refine``.
"""

from pipeline.refine.refine import RefineConfig, RefineResult, refine_rotations

__all__ = ["RefineConfig", "RefineResult", "refine_rotations"]
