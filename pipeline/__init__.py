"""Rotation averaging for structure from motion.

Conventions (see ``../shared/DESIGN.md``): ``R_i`` is cam_from_world, an edge
``(i, j)`` with ``i < j`` carries ``R_ij = R_j R_iᵀ``, perturbations are on the
left: ``R_j R_iᵀ = exp([Δω]×) R̃_ij`` and ``H_ij`` is the precision of ``Δω``.
"""

__version__ = "0.1.0"
