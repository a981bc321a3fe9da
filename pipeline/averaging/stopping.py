"""When a reweighted stage has converged: the cost and the largest camera update have both settled.

Paper 1 (§6) stops IRLS when the *mean* camera update is below 1e-3 rad. A mean over
many cameras hides the few that outliers still pull, and 1e-3 rad (0.057°) is coarse
on a graph resolved to 0.03° (fountain-P11) and fine on one resolved to 2° (the kNN
protocol). A stage here stops when **both**

- the relative decrease of its cost is at most ``ftol``: ``|f_prev − f| ≤ ftol·|f|``;
- the *largest* camera update is at most ``xtol_scale · σ̂`` (at least 1e-9 rad), where
  σ̂ = median(θ)/median(χ₃) is the robust per-axis scale of the current residual
  angles: a share of what the data can resolve, whatever that is; or at most
  ``tol_rad`` when that is given (an absolute threshold, e.g. for tests to 1e-12).

A plateau of the cost with one camera still moving (an outlier-pulled camera adds little
to a robust cost) is not convergence, nor is one small step on a cost that still falls.
Pure functions; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.config import Config, option

__all__ = ["StopRule", "StopConfig", "converged", "robust_scale", "CHI3_MEDIAN"]

#: Least update threshold of the scale-relative rule (exact data: σ̂ → 0), radians.
XTOL_FLOOR = 1e-9
#: Median of the χ distribution with 3 degrees of freedom: median ‖z‖ for z ~ N(0, I₃).
CHI3_MEDIAN = 1.5382


@dataclass(frozen=True)
class StopRule:
    """Stop a reweighted stage when its cost and its largest camera update have settled.

    Attributes:
        ftol: relative cost decrease below which the cost has settled.
        xtol_scale: largest camera update, as a share of the robust residual scale σ̂.
        tol_rad: an absolute threshold on the largest update (radians) in place of
            ``xtol_scale · σ̂``, or None.
        max_iterations: iteration cap.
    """

    ftol: float = 1e-5
    xtol_scale: float = 0.05
    tol_rad: float | None = None
    max_iterations: int = 100

    def xtol(self, sigma_rad: float) -> float:
        """The update threshold (radians) for a robust residual scale ``sigma_rad``."""
        return self.tol_rad if self.tol_rad is not None else max(XTOL_FLOOR, self.xtol_scale * sigma_rad)


def converged(f_prev: float, f: float, max_step_rad: float, rule: StopRule, sigma_rad: float = 0.0,
              theta: np.ndarray | None = None) -> bool:
    """True when ``max_step_rad ≤ rule.xtol(sigma_rad)`` and the cost has settled, ``|f_prev − f| ≤ ftol·|f|``.

    A largest step of at most :data:`XTOL_FLOOR` also counts as settled: on exact data the
    cost falls towards 0 by a large factor every step, so its relative decrease never
    settles while nothing moves any more.

    With the residual angles ``theta`` given, σ̂ is :func:`robust_scale` of them, taken only where the answer needs
    it (a settled cost and no ``tol_rad``): a median of every edge's residual, which most iterations can skip.
    """
    settled = abs(f_prev - f) <= rule.ftol * max(abs(f), 1e-300) or max_step_rad <= XTOL_FLOOR
    if not settled:
        return False
    if theta is not None and rule.tol_rad is None:
        sigma_rad = robust_scale(theta)
    return bool(max_step_rad <= rule.xtol(sigma_rad))


def robust_scale(theta: np.ndarray) -> float:
    """σ̂ per axis from residual angles ``theta`` (M,) radians: median(θ)/median(χ₃), at least 1e-12."""
    return max(float(np.median(theta)) / CHI3_MEDIAN, 1e-12) if np.size(theta) else 1e-12


@dataclass(frozen=True, kw_only=True)
class StopConfig(Config):
    """The stopping options shared by the iterative methods (module docstring)."""

    max_iterations: int = option(100, "iteration cap of the main reweighted stage", ge=0)
    ftol: float = option(1e-5, "stop when the cost's relative decrease is below this ...", ge=0)
    xtol_scale: float = option(0.05, "... and the largest camera update is below this share of the robust "
                                     "residual scale σ̂", ge=0)
    tol_rad: float | None = option(None, "an absolute threshold on the largest update instead (radians); "
                                         "null: xtol_scale × σ̂", ge=0)

    def stop_rule(self, max_iterations: int | None = None, xtol_scale: float | None = None) -> StopRule:
        """The :class:`StopRule` of these options (another cap or update share for the polish)."""
        return StopRule(self.ftol, self.xtol_scale if xtol_scale is None else xtol_scale, self.tol_rad,
                        self.max_iterations if max_iterations is None else max_iterations)
