"""MATLAB ``.mat`` view graphs: the LU Sphinx layout and the ℓ1-averaging layout.

Camera names are the 0-based indices as strings (``"0"``, ``"1"``, …).

**LU Sphinx layout** (paper 2's repository, ``../shared/data/lu_sphinx``):

- ``Rgt`` (3N, 3): stacked ground-truth cam_from_world rotations, block i in rows
  3i…3i+2.
- ``Rrel`` (3N, 3N): block (i, j), i < j, is the measured ``R̃_ij ≈ R_j R_iᵀ``;
  all-zero blocks mean "no edge".
- ``Alpha`` (3N, 3N, optional): block (i, j) is ``M_ij``; the precision is
  ``H_ij = tr(M_ij)·I − M_ij`` (paper 2, eq. 4–5).

  Convention, checked on LU Sphinx (``tests/test_io.py``): ``H_ij`` is the
  precision of the LEFT perturbation ``R_j R_iᵀ = exp([Δω]×) R̃_ij``, the
  project's convention. Against ``Rgt`` the Gaussian log-likelihood of the
  left residuals is higher than that of the right ones (``R̃ᵀ R_j R_iᵀ``).
  The file's H carries an arbitrary global scale (about 1/1.2·10⁵ of the
  precision implied by the residuals against ``Rgt``); it is kept as stored,
  since paper 2's cost and its Mahalanobis error (eq. C.13) use it as stored.

**ℓ1 layout** (public ℓ1 / IRLS rotation-averaging code):

- ``RR`` (3, 3, M): ``RR[:, :, k] ≈ R_j R_iᵀ`` for ``(i, j) = I[:, k]``.
- ``I`` (2, M): 1-based camera indices, either orientation of each pair; an ``I`` stored M×2
  (one edge a row) is read as its transpose when M ≠ 2 matches RR.
- ``Rgt`` (3, 3, N, optional): cam_from_world truth; an all-zero (or all-NaN, as the ℓ1 code
  writes the cameras it did not solve) block marks a camera without ground truth.
- ``RR`` and ``Rgt`` may also be 4×M and 4×N quaternions, scalar first: the ℓ1 code
  (``AverageSO3Graph``) takes either form (its ``q2R``: ``q = (cos θ/2, sin θ/2 · n)``).
- ``H`` (3, 3, M, optional): precisions, an addition of this project written by
  :func:`write_l1_mat` when the view graph has them.

**Near-rotations.** Public sets store their rotations to about 1e-6 (the Ellis Island
graph of 1DSfM in the ℓ1 layout: ``det = 0.999999``). Blocks within ``rotation_tol``
(default 1e-3, :mod:`pipeline.io.near_rotation`) of SO(3) are projected onto it, with
ONE warning per file giving the count and the largest deviation; beyond it they are
refused, naming the block.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io as sio

from pipeline.core import so3
from pipeline.core.atomic import atomic_path
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, OneWarning

logger = logging.getLogger(__name__)

__all__ = ["MatData", "read_lu_sphinx", "read_l1_mat", "write_l1_mat", "read_mat", "read_input_graph"]


@dataclass
class MatData:
    """A view graph read from a file, with its ground truth when the file has one.

    Attributes:
        vg: the view graph (names "0", "1", …).
        R_gt: (N, 3, 3) cam_from_world ground truth (identity where missing) or None.
        gt_mask: (N,) True where the ground truth exists, or None.
    """

    vg: ViewGraph
    R_gt: np.ndarray | None
    gt_mask: np.ndarray | None


def _loadmat_arrays(path: str) -> dict[str, Any]:
    """The variables of a .mat file: numeric arrays (sparse ones densified), others as their type name.

    Runs in a sandboxed child process (:mod:`pipeline.core.sandbox`): scipy's reader
    crashes the process (SIGSEGV) on some damaged files (scipy 1.17, two flipped bytes).
    """
    out: dict[str, Any] = {}
    for k, v in sio.loadmat(path, squeeze_me=False).items():
        if k.startswith("__"):
            continue
        if hasattr(v, "toarray") and not isinstance(v, np.ndarray):  # a MATLAB sparse variable
            v = v.toarray()
        out[k] = v if isinstance(v, np.ndarray) and v.dtype.kind in "fiub" else type(v).__name__
    return out


def _load(path: str | os.PathLike) -> tuple[Path, dict[str, Any]]:
    from pipeline.core.sandbox import SandboxError, run_limited  # noqa: PLC0415

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f".mat file {path} does not exist")
    size = path.stat().st_size
    try:
        data = run_limited(_loadmat_arrays, str(path), timeout=60 + size / 1e6, memory_bytes=(3 << 30) + 64 * size,
                           preload=("numpy", "scipy.io", __name__))
    except SandboxError as exc:
        if str(exc).startswith("NotImplementedError"):  # MATLAB v7.3 files are HDF5
            raise InputFileError(f"{path} is a MATLAB v7.3 (HDF5) file; re-save it in MATLAB with save(..., '-v7')"
                                 ) from None
        raise InputFileError(f"{path} is not a readable .mat file ({exc})") from None
    return path, data


def _numeric(path: Path, data: dict[str, Any], key: str, allow_nan: bool = False) -> np.ndarray:
    a = data[key]
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiub":
        got = a if isinstance(a, str) else type(a).__name__
        raise InputFileError(f"{path}: variable {key!r} must be a numeric array, got {got}")
    a = np.asarray(a, dtype=np.float64)
    if not np.all(np.isfinite(a) | (allow_nan & np.isnan(a))):
        raise InputFileError(f"{path}: variable {key!r} has NaN or inf entries")
    return a


def _is_quaternions(a: np.ndarray) -> bool:
    """A 4×K variable: K quaternions, scalar first, as the ℓ1 code (AverageSO3Graph) also takes RR and Rgt."""
    return a.ndim == 2 and a.shape[0] == 4


def _ground_truth(path: Path, blocks: np.ndarray, near: OneWarning) -> tuple[np.ndarray, np.ndarray]:
    """Validate (N, 3, 3) truth blocks, or (N, 4) quaternions; all-zero or all-NaN ones (the ℓ1 code writes NaN for the
    cameras it did not solve) become identity + mask False."""
    flat = blocks.reshape(blocks.shape[0], -1)
    nan = np.isnan(flat)
    partial = nan.any(axis=1) & ~nan.all(axis=1)
    if partial.any():
        raise InputFileError(f"{path}: the Rgt block of camera {int(np.flatnonzero(partial)[0])} is partly NaN; a "
                             "camera without truth is all zeros (or all NaN)")
    mask = ~nan.any(axis=1) & (np.abs(np.nan_to_num(flat)).sum(axis=1) > 0)
    R = np.broadcast_to(np.eye(3), (blocks.shape[0], 3, 3)).copy()
    if mask.any():
        labels = [f"of camera {k}" for k in np.flatnonzero(mask)]
        R[mask] = so3.matrix_from_quat(near.quaternions(flat[mask], "Rgt", labels)) if flat.shape[1] == 4 else \
            near.rotations(blocks[mask], "Rgt block", labels)
    return R, mask


def _make_graph(path: Path, names: list[str], edges: np.ndarray, R_rel: np.ndarray, H: np.ndarray | None) -> ViewGraph:
    n = len(names)
    if edges.shape[0] == 0:
        raise InputFileError(f"{path} holds no edges (no relative rotations); nothing to average")
    deg = np.bincount(edges.ravel(), minlength=n) if edges.size else np.zeros(n, int)
    isolated = int(np.sum(deg == 0))
    if isolated:
        logger.warning("%s: %d of %d cameras have no edge; they are kept (restrict to the largest component)", path, isolated, n)
    try:
        return ViewGraph.from_edges(names, edges, R_rel, H=H, allow_isolated=isolated > 0)
    except ViewGraphError as exc:
        raise InputFileError(f"{path}: {exc}") from exc


def read_lu_sphinx(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL,
                   _loaded: tuple[Path, dict[str, Any]] | None = None) -> MatData:
    """Read the LU Sphinx layout (``Rgt``, ``Rrel``, optional ``Alpha``).

    Args:
        path: a ``.mat`` file.

    Args:
        path: a ``.mat`` file.
        rotation_tol: blocks within this of SO(3) are projected (one warning), beyond refused.

    Returns:
        MatData with ``H_ij = tr(M_ij)·I − M_ij`` (symmetrized) when ``Alpha`` is present.

    Raises:
        InputFileError: missing variables, shapes that are not multiples of 3,
            non-rotation blocks, or H that is not positive definite.
    """
    path, data = _loaded or _load(path)  # read_mat passes what it loaded: one read
    if "Rrel" not in data:
        raise InputFileError(f"{path}: no variable 'Rrel'; the LU Sphinx layout needs Rrel (3N×3N), found {sorted(data)}")
    Rrel = _numeric(path, data, "Rrel")
    if Rrel.ndim != 2 or Rrel.shape[0] != Rrel.shape[1] or Rrel.shape[0] % 3:
        raise InputFileError(f"{path}: Rrel.shape={Rrel.shape} but expected (3N, 3N)")
    n = Rrel.shape[0] // 3
    # blocks[i, j] = Rrel[3i:3i+3, 3j:3j+3]
    blocks = Rrel.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
    present = np.abs(blocks).sum(axis=(2, 3)) > 0
    if np.any(np.diag(present)):
        k = int(np.flatnonzero(np.diag(present))[0])
        raise InputFileError(f"{path}: Rrel has a non-zero diagonal block ({k}, {k}); diagonal blocks must be zero (no self-edges)")
    # Both (i, j) and (j, i) given: keep the upper block, as the layout stores i < j.
    lower_dup = np.tril(present, -1) & present.T
    if np.any(lower_dup):
        logger.info("%s: %d pairs stored in both triangles; using the upper blocks", path, int(lower_dup.sum()))
    present &= ~lower_dup
    i, j = np.nonzero(present)
    edges = np.stack([i, j], axis=1)
    near = OneWarning(path, rotation_tol, advise=True)
    R_rel = near.rotations(blocks[i, j], "Rrel block", [f"({a}, {b})" for a, b in zip(i, j)])
    H = None
    if "Alpha" in data:
        Alpha = _numeric(path, data, "Alpha")
        if Alpha.shape != Rrel.shape:
            raise InputFileError(f"{path}: Alpha.shape={Alpha.shape} but expected Rrel's shape {Rrel.shape}")
        M = Alpha.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)[i, j]
        # The file stores M to single-precision symmetry; H must be symmetric.
        with np.errstate(all="ignore"):  # absurd entries give inf/NaN, which the view graph refuses
            M = 0.5 * (M + np.swapaxes(M, 1, 2))
            H = np.trace(M, axis1=1, axis2=2)[:, None, None] * np.eye(3) - M  # paper 2, eq. 4
        # An edge stored as (j, i) carries M_ji; from_edges turns H into that of (i, j).
    R_gt = gt_mask = None
    if "Rgt" in data:
        Rgt = _numeric(path, data, "Rgt")
        if Rgt.shape != (3 * n, 3):
            raise InputFileError(f"{path}: Rgt.shape={Rgt.shape} but expected ({3 * n}, 3) for {n} cameras")
        R_gt, gt_mask = _ground_truth(path, Rgt.reshape(n, 3, 3), near)
    vg = _make_graph(path, [str(k) for k in range(n)], edges, R_rel, H)
    near.warn()
    return MatData(vg, R_gt, gt_mask)


def _stack3(path: Path, a: np.ndarray, key: str) -> np.ndarray:
    """(3, 3, K) MATLAB array → (K, 3, 3); MATLAB drops a trailing singleton K."""
    if a.ndim == 2 and a.shape == (3, 3):
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[:2] != (3, 3):
        raise InputFileError(f"{path}: {key}.shape={a.shape} but expected (3, 3, K)")
    return np.ascontiguousarray(np.moveaxis(a, 2, 0))


def read_l1_mat(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL,
                _loaded: tuple[Path, dict[str, Any]] | None = None) -> MatData:
    """Read the ℓ1 layout (``RR`` 3×3×M, ``I`` 2×M 1-based, optional ``Rgt`` 3×3×N).

    Args:
        path: a ``.mat`` file.
        rotation_tol: blocks within this of SO(3) are projected (one warning), beyond refused.

    Returns:
        MatData; N is the size of ``Rgt`` when present, else the largest index in ``I``.

    Raises:
        InputFileError: missing variables, bad shapes, indices that are not
            positive integers or exceed N, non-rotation blocks.
    """
    path, data = _loaded or _load(path)  # read_mat passes what it loaded: one read
    missing = [k for k in ("RR", "I") if k not in data]
    if missing:
        raise InputFileError(f"{path}: missing {missing}; the ℓ1 layout needs RR (3×3×M) and I (2×M), found {sorted(data)}")
    RR = _numeric(path, data, "RR")
    quaternions = _is_quaternions(RR)
    RR = RR.T if quaternions else _stack3(path, RR, "RR")
    I = _numeric(path, data, "I")
    if I.ndim == 2 and I.shape == (RR.shape[0], 2) and I.shape[0] != 2:  # stored M×2 (one edge a row): unambiguous
        logger.info("%s: I is stored %d×2 (one edge a row); read as its transpose", path, I.shape[0])
        I = I.T
    if I.ndim != 2 or I.shape[0] != 2:
        raise InputFileError(f"{path}: I.shape={I.shape} but expected (2, M) (or (M, 2)) for the {RR.shape[0]} blocks "
                             "of RR")
    if I.shape[1] != RR.shape[0]:
        raise InputFileError(f"{path}: I has {I.shape[1]} columns but RR has {RR.shape[0]} blocks; they must match")
    if np.any(I != np.round(I)) or (I.size and (I.min() < 1 or I.max() >= 2 ** 31)):
        raise InputFileError(f"{path}: I must hold 1-based integer camera indices (>= 1)")
    edges = I.T.astype(np.int64) - 1
    near = OneWarning(path, rotation_tol, advise=True)
    labels = [f"{k + 1} (1-based)" for k in range(RR.shape[0])]
    RR = so3.matrix_from_quat(near.quaternions(RR, "RR", labels)) if quaternions else \
        near.rotations(RR, "RR block", labels)
    R_gt = gt_mask = None
    if "Rgt" in data:
        Rgt = _numeric(path, data, "Rgt", allow_nan=True)
        Rgt = Rgt.T if _is_quaternions(Rgt) else _stack3(path, Rgt, "Rgt")
        n = Rgt.shape[0]
        R_gt, gt_mask = _ground_truth(path, Rgt, near)
    else:
        n = int(edges.max()) + 1 if edges.size else 0
        used = len(np.unique(edges))
        if n > 10 * used + 1000:  # every camera up to the largest index would be allocated, nearly all isolated
            raise InputFileError(f"{path}: I refers to camera {n} but only {used} distinct cameras have an edge; "
                                 "without Rgt the largest index is the camera count, so this index is a mistake "
                                 "(check I, or add Rgt 3x3xN)")
    if edges.size and edges.max() >= n:
        raise InputFileError(f"{path}: I refers to camera {int(edges.max()) + 1} but Rgt has only {n} cameras; Rgt "
                             "must hold a 3×3 block for every camera (3×3×N, all zeros where the truth is unknown)")
    H = None
    if "H" in data:
        H = _stack3(path, _numeric(path, data, "H"), "H")
        if H.shape[0] != RR.shape[0]:
            raise InputFileError(f"{path}: H has {H.shape[0]} blocks but RR has {RR.shape[0]}")
    vg = _make_graph(path, [str(k) for k in range(n)], edges, RR, H)
    near.warn()
    return MatData(vg, R_gt, gt_mask)


def write_l1_mat(path: str | os.PathLike, vg: ViewGraph, R_gt: np.ndarray | None = None) -> Path:
    """Write a view graph in the ℓ1 layout, atomically.

    Args:
        path: output ``.mat`` file.
        vg: view graph; its cameras are written in order (index k ↔ name k).
        R_gt: (N, 3, 3) ground truth; rows with NaN are written as zero blocks
            (no ground truth).

    Returns:
        The path written.
    """
    arrays: dict[str, np.ndarray] = {
        "RR": np.moveaxis(vg.R_rel, 0, 2),
        "I": (vg.edges.T + 1).astype(np.float64),
    }
    if R_gt is not None:
        R_gt = np.asarray(R_gt, dtype=np.float64)
        if R_gt.shape != (vg.n_cameras, 3, 3):
            raise ValueError(f"R_gt.shape={R_gt.shape} but expected ({vg.n_cameras}, 3, 3)")
        R_gt = np.where(np.isfinite(R_gt).all(axis=(1, 2))[:, None, None], R_gt, 0.0)
        arrays["Rgt"] = np.moveaxis(R_gt, 0, 2)
    if vg.H is not None:
        arrays["H"] = np.moveaxis(vg.H, 0, 2)
    with atomic_path(path, suffix=".mat") as tmp:
        sio.savemat(tmp, arrays, do_compression=True)
    return Path(path)


def read_mat(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL) -> MatData:
    """Read a ``.mat`` view graph, detecting the layout from its variables.

    ``Rrel`` → LU Sphinx layout; ``RR`` and ``I`` → ℓ1 layout.
    """
    p, data = _load(path)
    if "Rrel" in data:
        return read_lu_sphinx(p, rotation_tol, _loaded=(p, data))
    if "RR" in data and "I" in data:
        return read_l1_mat(p, rotation_tol, _loaded=(p, data))
    raise InputFileError(
        f"{p}: unknown .mat layout with variables {sorted(data)}; expected Rrel (+Rgt, Alpha) "
        "as in LU Sphinx, or RR and I (+Rgt) as in the ℓ1 layout"
    )


def read_input_graph(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL) -> MatData:
    """Read a view graph to average from any supported input (:func:`pipeline.io.graphs.read_input_graph`)."""
    from pipeline.io.graphs import read_input_graph as read  # noqa: PLC0415 - graphs imports this module

    return read(path, rotation_tol)
