"""Accept matrices and quaternions that are rotations up to the precision of a text file.

Files written with 6–7 significant digits (1DSfM's ``EGs.txt``, GLOMAP's rotation files,
the public ℓ1 ``.mat`` sets with ``RR`` at ~1e-6) hold matrices whose ``max|RᵀR − I|`` is
~1e-6 and determinants 0.999999, which the project's strict check (``ViewGraph``:
``ROTATION_TOL = 1e-6``; ``read_rotations``: 1e-6; ``.mat`` truth and references: 1e-5)
refuses. This module projects such inputs onto SO(3) and warns once per input.

**Measure.** ``dev(R) = max_ab |(RᵀR − I)_ab|``, the measure the project already prints
("max|RᵀR−I|=1.09e-06"). For ``R = R₀ + E`` with ``R₀ ∈ SO(3)``, ``RᵀR − I ≈ R₀ᵀE + EᵀR₀``:
twice the symmetric part of the error, so the default 1e-3 admits entry errors of ~5e-4 and
the projection (SVD, determinant fixed) changes R by about as much (‖ΔR‖_F ~ 1e-3, the
report's ``max_change``). ``det R`` must be positive (a reflection is never
"near" a rotation). Quaternions: ``| ‖q‖ − 1 |`` with the same tolerance (q is normalized;
``‖q‖² − 1`` is the quaternion analogue of ``RᵀR − I``).

**Where it applies.** ``ViewGraph.validate`` stays strict (``ROTATION_TOL = 1e-6``: it
guards an internal invariant); every reader of a user file projects its rotations with
:func:`project_near_rotations` before building the view graph, with a ``rotation_tol``
argument (``python -m pipeline.average --rotation-tol``, default
:data:`DEFAULT_ROTATION_TOL`): the ``.mat`` layouts (:mod:`pipeline.io.mat`), rotations
files (:mod:`pipeline.io.rotations`), 1DSfM, g2o and GLOMAP files. A reader of an input in parts (the ``.mat``
layouts' variables, a 1DSfM folder's ``EGs.txt`` and ``gt_bundle.out``) projects each part through
:class:`OneWarning`, which warns once for the input.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.core.errors import InputFileError

__all__ = ["DEFAULT_ROTATION_TOL", "NearRotationError", "NearRotationReport", "rotation_deviation",
           "project_near_rotations", "normalize_near_unit_quaternions", "projected_or_input_error", "OneWarning"]

logger = logging.getLogger(__name__)

#: Largest max|RᵀR − I| (or |‖q‖ − 1|) projected instead of refused.
DEFAULT_ROTATION_TOL = 1e-3
#: Deviations at or below this are treated as exact (not counted in the warning).
EXACT_TOL = 1e-12


class NearRotationError(ValueError):
    """A matrix that is not within the tolerance of SO(3) (message: one line)."""


@dataclass
class NearRotationReport:
    """What :func:`project_near_rotations` did.

    Attributes:
        n_total: matrices examined.
        n_projected: matrices with a deviation above ``EXACT_TOL`` that were projected.
        max_deviation: largest max|RᵀR − I| (or | ‖q‖ − 1 |) seen.
        max_change: largest Frobenius distance ‖P(R) − R‖_F between an input and its projection.
    """

    n_total: int
    n_projected: int
    max_deviation: float
    max_change: float


def rotation_deviation(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``max|RᵀR − I|`` and ``det R`` for (..., 3, 3) matrices (inf / NaN for non-finite input)."""
    R = np.asarray(R, dtype=np.float64)
    finite = np.all(np.isfinite(R), axis=(-2, -1))
    Rf = np.where(finite[..., None, None], R, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):  # entries near the float limit: far from SO(3), no warning
        dev = np.max(np.abs(np.swapaxes(Rf, -1, -2) @ Rf - np.eye(3)), axis=(-2, -1))
        det = np.linalg.det(Rf)
    return np.where(finite, dev, np.inf), np.where(finite, det, np.nan)


def _describe(k: int, labels: list[str] | None) -> str:
    return labels[k] if labels is not None else f"#{k}"


def project_near_rotations(R: np.ndarray, tol: float = DEFAULT_ROTATION_TOL, *, what: str = "rotation",
                           source: str = "input", labels: list[str] | None = None,
                           warn: bool = True) -> tuple[np.ndarray, NearRotationReport]:
    """Project matrices within ``tol`` of SO(3) onto it; refuse the others.

    Args:
        R: (K, 3, 3) matrices.
        tol: largest accepted ``max|RᵀR − I|``.
        what: what the matrices are, for messages (e.g. ``"relative rotation"``).
        source: the file (or variable) they came from, named in messages.
        labels: optional K labels (e.g. ``"edge (3, 7)"``) for the first offender.
        warn: log ONE warning with the count and the largest deviation when any matrix
            deviates by more than ``EXACT_TOL``.

    Returns:
        (K, 3, 3) rotations and a :class:`NearRotationReport`.

    Raises:
        NearRotationError: a non-finite matrix, a negative determinant, or a deviation above
            ``tol`` (one line naming ``source``, the first offender and the tolerance).
    """
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol={tol!r} but expected a finite value >= 0")
    dev, det = rotation_deviation(R)
    bad = ~(np.isfinite(dev) & (det > 0) & (dev <= tol))
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        if not np.isfinite(dev[k]):
            why = "is not a rotation (or has NaN): it has NaN or inf entries"
        elif not det[k] > 0:
            why = f"is not a rotation: det={det[k]:.6g} (a reflection or degenerate)"
        else:
            why = f"is not a rotation: max|RᵀR−I|={dev[k]:.3g} > tolerance {tol:g}"
        n_bad = int(bad.sum())
        more = f" ({n_bad} such matrices)" if n_bad > 1 else ""
        raise NearRotationError(f"{source}: {what} {_describe(k, labels)} {why}{more}")
    near = dev > EXACT_TOL
    out = R.copy()
    change = 0.0
    if np.any(near):
        P = so3.project_to_so3(R[near])
        change = float(np.sqrt(np.square(P - R[near]).sum(axis=(1, 2))).max())
        out[near] = P
    rep = NearRotationReport(int(R.shape[0]), int(near.sum()), float(dev.max()) if dev.size else 0.0, change)
    if warn and rep.n_projected:
        logger.warning("%s: %d of %d %s matrices deviate from SO(3) (largest max|RᵀR−I| %.3g, tolerance %g); "
                       "projected onto SO(3)", source, rep.n_projected, rep.n_total, what, rep.max_deviation, tol)
    return out, rep


def normalize_near_unit_quaternions(q: np.ndarray, tol: float = DEFAULT_ROTATION_TOL, *, source: str = "input",
                                    labels: list[str] | None = None, warn: bool = True
                                    ) -> tuple[np.ndarray, NearRotationReport]:
    """Normalize quaternions whose norm is within ``tol`` of 1; refuse the others.

    Args:
        q: (K, 4) quaternions in any component order (only the norm is used).
        tol, source, labels, warn: as :func:`project_near_rotations`.

    Returns:
        (K, 4) unit quaternions and a report (``max_change``: largest | ‖q‖ − 1 |).
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    nrm = np.linalg.norm(q, axis=1)
    dev = np.where(np.all(np.isfinite(q), axis=1), np.abs(nrm - 1.0), np.inf)
    bad = ~(dev <= tol)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        why = "has NaN or inf entries" if not np.isfinite(dev[k]) else \
            f"has norm {nrm[k]:.6g}, not within {tol:g} of 1"
        raise NearRotationError(f"{source}: quaternion {_describe(k, labels)} {why}")
    near = dev > EXACT_TOL
    mx = float(dev.max()) if dev.size else 0.0
    rep = NearRotationReport(int(q.shape[0]), int(near.sum()), mx, mx)
    if warn and rep.n_projected:
        logger.warning("%s: %d of %d quaternions are not unit (largest | |q| − 1 | %.3g, tolerance %g); normalized",
                       source, rep.n_projected, rep.n_total, rep.max_deviation, tol)
    return q / nrm[:, None], rep


def projected_or_input_error(R: np.ndarray, tol: float, *, what: str, source: str,
                             labels: list[str] | None = None) -> np.ndarray:
    """:func:`project_near_rotations`, with a refusal turned into one :class:`InputFileError` line."""
    try:
        return project_near_rotations(R, tol, what=what, source=source, labels=labels)[0]
    except NearRotationError as exc:
        raise InputFileError(str(exc)) from None


@dataclass
class OneWarning:
    """The near-rotations of one input read in parts (a ``.mat`` file's variables, a 1DSfM folder's files), each
    projected as it is read, with ONE warning for the input when all are read (:meth:`warn`): ``<source>: 3 of 40 RR
    blocks and 2 of 9 Rgt blocks deviate from SO(3) (largest max|RᵀR−I| 1.2e-06, tolerance 0.001); projected onto
    SO(3)``.

    Args:
        source: the input, named in the warning.
        tol: the tolerance (``max|RᵀR − I|``, or ``| ‖q‖ − 1 |``).
        advise: a refusal also says what was expected and that ``--rotation-tol`` accepts coarser inputs.
    """

    source: str | os.PathLike
    tol: float
    advise: bool = False
    parts: list[str] = field(default_factory=list)
    worst: float = 0.0

    def rotations(self, R: np.ndarray, what: str, labels: list[str] | None = None,
                  source: str | os.PathLike | None = None) -> np.ndarray:
        """(K, 3, 3) matrices ``what`` (e.g. ``"RR block"``) projected onto SO(3); a refusal is one
        :class:`InputFileError` line. ``source``: the file they came from, when not the input itself (the warning
        then names it: ``"12 of 40 EG rotations of EGs.txt"``)."""
        try:
            out, rep = project_near_rotations(R, self.tol, what=what, source=str(source or self.source), labels=labels,
                                              warn=False)
        except NearRotationError as exc:
            raise InputFileError(f"{exc}{self._advice('rotations')}") from None
        self._add(rep, f"{what}s" + ("" if source is None else f" of {Path(source).name}"))
        return out

    def quaternions(self, q: np.ndarray, key: str, labels: list[str] | None = None) -> np.ndarray:
        """(K, 4) quaternions of the variable ``key`` normalized (:func:`normalize_near_unit_quaternions`); a refusal
        is one :class:`InputFileError` line."""
        try:
            out, rep = normalize_near_unit_quaternions(q, self.tol, source=str(self.source), labels=labels,
                                                       warn=False)
        except NearRotationError as exc:
            raise InputFileError(f"{exc}{self._advice('unit quaternions')}") from None
        self._add(rep, f"{key} quaternions (| |q| − 1 |)")
        return out

    def warn(self) -> None:
        """The one warning (none when nothing deviated)."""
        if self.parts:
            logger.warning("%s: %s deviate from SO(3) (largest max|RᵀR−I| %.3g, tolerance %g); projected onto SO(3)",
                           self.source, " and ".join(self.parts), self.worst, self.tol)

    def _add(self, rep: NearRotationReport, part: str) -> None:
        if rep.n_projected:
            self.parts.append(f"{rep.n_projected} of {rep.n_total} {part}")
            self.worst = max(self.worst, rep.max_deviation)

    def _advice(self, expected: str) -> str:
        return f"; expected {expected} (raise --rotation-tol to accept coarser ones)" if self.advise else ""
