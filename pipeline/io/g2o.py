"""Rotation graphs in the g2o text format (as read by GTSAM, SE-Sync, g2o).

Lines (established from GTSAM's ``gtsam/slam/dataset.cpp`` and g2o's ``types/slam3d``):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw``: pose ``T_id = (R, t)`` **world_from_body**
  (quaternion x, y, z, w; Hamilton).
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw I11 I12 … I66``: measurement of ``T_i⁻¹ T_j`` and
  the 21 upper-triangular entries (row by row) of the 6×6 information matrix in g2o's order
  **(translation, rotation)**. GTSAM's ``readG2o`` swaps the blocks into its Pose3 tangent
  order (rotation, translation) and uses them unscaled as the information of
  ``Logmap(Z̃⁻¹ T_i⁻¹ T_j)`` (rotation in radians); verified on gtsam 4.3 (test).
* g2o itself computes the error as ``toVectorMQT(Z̃⁻¹ T_i⁻¹ T_j)``: the rotation part is the
  vector part of the unit quaternion, ≈ ω/2. The same file therefore means a rotation
  information **4×** larger to g2o than to GTSAM. ``info_convention="gtsam"`` (default, also
  what SE-Sync-style rotation-averaging readers assume) or ``"g2o"`` selects the meaning.
* ``EDGE_SO3:QUAT i j qx qy qz qw I11 … I33`` (6 entries): not standard. GTSAM 4.3's
  ``readG2o`` ignores it silently (checked); one public research code base writes it. It is
  read here (same conventions, rotation block only) and written on request.

**H in their frame.** Our cameras ``R_i`` are cam_from_world, so the g2o/GTSAM pose is
``T_i = (R_iᵀ, c_i)`` and an edge's measured rotation is ``Z̃ = R̃_ijᵀ`` (``T_i⁻¹T_j`` has rotation
``R_i R_jᵀ = (R_j R_iᵀ)ᵀ``). GTSAM's error is ``ξ = Log(Z̃ᵀ R_i R_jᵀ) = Log(R̃_ij R_i R_jᵀ)``, and
with our left perturbation ``R_j R_iᵀ = exp([Δω]×) R̃_ij``, ``R̃_ij R_i R_jᵀ = (R_j R_iᵀ R̃_ijᵀ)ᵀ =
exp(−[Δω]×)``, so ``ξ = −Δω`` exactly: **the rotation block is H itself** (no rotation, no
transpose; the sign flip leaves ``ξᵀHξ`` unchanged), and 4H in g2o's own convention. The test
writes a graph with anisotropic H, solves it with GTSAM's LM from the file GTSAM read, and
matches this project's anisotropic least-squares solution.

**A coupled information matrix** (a pose graph whose edges tie rotation and translation errors) gives the
rotation's *marginal* precision, the Schur complement ``I_rr − I_rt I_tt⁺ I_tr`` (the inverse of the rotation
block of the covariance), as the two-view BA's H is: rotation averaging estimates no translation, so the
translation measurement cannot be held fixed. Block-diagonal information (every file this project writes, and
GTSAM's diagonal noise models) gives ``I_rr`` itself.
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.common import repeated_pair
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, NearRotationError, normalize_near_unit_quaternions

__all__ = ["G2oData", "write_g2o", "read_g2o", "rotation_marginal", "INFO_CONVENTIONS"]

logger = logging.getLogger(__name__)

#: rotation-information scale: file block = scale · H (H: precision of ω in 1/rad²)
INFO_CONVENTIONS = {"gtsam": 1.0, "g2o": 4.0}
_IU6 = np.triu_indices(6)
_IU3 = np.triu_indices(3)


@dataclass
class G2oData:
    """A rotation graph read from a g2o file.

    Attributes:
        vg: view graph (names: vertex ids as strings), ``H`` from the rotation information.
        R_init: (N, 3, 3) cam_from_world rotations of the vertices (``R_iᵀ`` of the pose), or
            None when the file has no vertex.
        ids: (N,) vertex ids.
        counts: lines read per tag, ignored tags included.
    """

    vg: ViewGraph
    R_init: np.ndarray | None
    ids: np.ndarray
    counts: dict[str, int]


def _q_xyzw(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (..., 4) quaternions (x, y, z, w)."""
    q = so3.quat_from_matrix(R)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _from_xyzw(q: np.ndarray) -> np.ndarray:
    return so3.matrix_from_quat(np.concatenate([q[..., 3:], q[..., :3]], axis=-1))


def write_g2o(path: str | os.PathLike, vg: ViewGraph, R: np.ndarray | None = None, *,
              info_convention: str = "gtsam", translation_info: float = 1.0, isotropic_info: float = 1.0,
              so3_edges: bool = False, ids: np.ndarray | None = None) -> Path:
    """Write a rotation graph as g2o (zero translations).

    Args:
        path: output file.
        vg: view graph; its ``H`` (or ``isotropic_info``·I) becomes the rotation information.
        R: (N, 3, 3) cam_from_world estimates for the vertices (default identity).
        info_convention: ``"gtsam"`` (block = H) or ``"g2o"`` (block = 4H); module docstring.
        translation_info: diagonal of the translation information (the translations are all 0;
            GTSAM needs a positive-definite matrix).
        isotropic_info: rotation information when ``vg.H`` is None (1/rad²).
        so3_edges: write the non-standard ``EDGE_SO3:QUAT`` instead of ``EDGE_SE3:QUAT``.
        ids: (N,) vertex ids (default 0..N−1).
    """
    if info_convention not in INFO_CONVENTIONS:
        raise ValueError(f"info_convention={info_convention!r} but expected one of {sorted(INFO_CONVENTIONS)}")
    n, m = vg.n_cameras, vg.n_edges
    ids = np.arange(n) if ids is None else np.asarray(ids, dtype=np.int64)
    R = np.broadcast_to(np.eye(3), (n, 3, 3)) if R is None else np.asarray(R, float)
    H = vg.H if vg.H is not None else np.broadcast_to(isotropic_info * np.eye(3), (m, 3, 3))
    Hs = INFO_CONVENTIONS[info_convention] * 0.5 * (H + np.swapaxes(H, 1, 2))
    qv = _q_xyzw(np.swapaxes(R, 1, 2))                 # world_from_cam
    qe = _q_xyzw(np.swapaxes(vg.R_rel, 1, 2))          # T_i⁻¹T_j rotation = R̃_ijᵀ
    fmt = lambda a: " ".join(f"{x:.17g}" for x in a)  # noqa: E731
    path = Path(path)
    with atomic_open(path) as fh:
        for k in range(n):
            fh.write(f"VERTEX_SE3:QUAT {ids[k]} 0 0 0 {fmt(qv[k])}\n")
        for k, (i, j) in enumerate(vg.edges):
            if so3_edges:
                fh.write(f"EDGE_SO3:QUAT {ids[i]} {ids[j]} {fmt(qe[k])} {fmt(Hs[k][_IU3])}\n")
            else:
                info = np.zeros((6, 6))
                info[:3, :3] = translation_info * np.eye(3)
                info[3:, 3:] = Hs[k]
                fh.write(f"EDGE_SE3:QUAT {ids[i]} {ids[j]} 0 0 0 {fmt(qe[k])} {fmt(info[_IU6])}\n")
    return path


def rotation_marginal(info: np.ndarray) -> np.ndarray:
    """The rotation block's marginal precision of a (6, 6) information in g2o's (translation, rotation) order."""
    I_tt, I_tr, I_rr = info[:3, :3], info[:3, 3:], info[3:, 3:]
    if not I_tr.any():
        return I_rr.copy()
    return I_rr - I_tr.T @ np.linalg.pinv(I_tt, hermitian=True) @ I_tr


def read_g2o(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL, *,
             info_convention: str = "gtsam") -> G2oData:
    """Read the rotation part of a 3D g2o pose graph.

    ``EDGE_SE3:QUAT`` and ``EDGE_SO3:QUAT`` become edges (translations dropped, rotation
    information → H per ``info_convention``); ``VERTEX_SE3:QUAT`` gives the initial rotations;
    ``FIX`` and other tags are counted and skipped (one warning).

    Raises:
        InputFileError: missing file, a line with the wrong number of fields or non-numbers,
            an edge to an undeclared vertex (when vertices are declared), a repeated vertex id
            or camera pair, a quaternion far from unit norm, a rotation information block that is
            not symmetric positive definite (one line naming the file and line).
    """
    if info_convention not in INFO_CONVENTIONS:
        raise ValueError(f"info_convention={info_convention!r} but expected one of {sorted(INFO_CONVENTIONS)}")
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"g2o file {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path} is not a readable text file ({exc.__class__.__name__})") from None
    counts: Counter[str] = Counter()
    v_ids, v_q, v_lines = [], [], []
    e_ij, e_q, e_H, e_t, e_lines = [], [], [], [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        tag = parts[0]
        counts[tag] += 1
        if tag == "VERTEX_SE3:QUAT":
            want = 9
        elif tag == "EDGE_SE3:QUAT":
            want = 3 + 7 + 21
        elif tag == "EDGE_SO3:QUAT":
            want = 3 + 4 + 6
        else:
            continue
        if len(parts) != want:
            raise InputFileError(f"{path}:{lineno}: {tag} needs {want - 1} values, got {len(parts) - 1}")
        try:
            ids = [int(parts[1])] if tag.startswith("VERTEX") else [int(parts[1]), int(parts[2])]
            vals = np.array([float(x) for x in parts[1 + len(ids):]])
        except ValueError:
            raise InputFileError(f"{path}:{lineno}: {tag}: ids must be integers and the rest numbers") from None
        if not np.all(np.isfinite(vals)):
            raise InputFileError(f"{path}:{lineno}: NaN or inf value; fix or delete the line")
        if tag == "VERTEX_SE3:QUAT":
            v_ids.append(ids[0])
            v_q.append(vals[3:7])
            v_lines.append(lineno)
            continue
        if ids[0] == ids[1]:
            raise InputFileError(f"{path}:{lineno}: an edge from vertex {ids[0]} to itself; delete the line")
        if tag == "EDGE_SE3:QUAT":
            t, q, up = vals[:3], vals[3:7], vals[7:]
            info = np.zeros((6, 6))
            info[_IU6] = up
            info = info + np.triu(info, 1).T
            Hb = rotation_marginal(info)
        else:
            t, q, up = np.zeros(3), vals[:4], vals[4:]
            Hb = np.zeros((3, 3))
            Hb[_IU3] = up
            Hb = Hb + np.triu(Hb, 1).T
        e_ij.append(ids)
        e_q.append(q)
        e_H.append(Hb / INFO_CONVENTIONS[info_convention])
        e_t.append(t)
        e_lines.append(lineno)
    ignored = {k: c for k, c in counts.items() if k not in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "EDGE_SO3:QUAT")}
    if not e_ij:
        flat = sorted(k for k in ignored if "SE2" in k)  # VERTEX_SE2, EDGE_SE2, EDGE_SE2_XY, ...
        if flat:  # one line, without the warning about the skipped lines
            raise InputFileError(f"{path} is a 2D pose graph ({', '.join(flat)} lines); this project averages 3D "
                                 "rotations: give a 3D graph (EDGE_SE3:QUAT edges)")
        raise InputFileError(f"{path} holds no EDGE_SE3:QUAT or EDGE_SO3:QUAT line; nothing to average (give a 3D "
                             "pose graph)")
    if ignored:
        logger.warning("%s: skipped %s", path, ", ".join(f"{c} {k} line(s)" for k, c in sorted(ignored.items())))
    e_ij = np.array(e_ij, dtype=np.int64)
    rep = repeated_pair(e_ij)
    if rep is not None:  # named by the file's vertex ids and lines
        a, b = rep
        raise InputFileError(f"{path}:{e_lines[b]}: vertices {e_ij[b, 0]} and {e_ij[b, 1]} already have an edge on line "
                             f"{e_lines[a]}; each pair may appear once, in either orientation: delete one of the lines")
    if v_ids:
        uniq, n_decl = np.unique(np.asarray(v_ids, dtype=np.int64), return_counts=True)
        if np.any(n_decl > 1):
            raise InputFileError(f"{path}: vertex id {int(uniq[np.argmax(n_decl > 1)])} declared twice")
        order = np.argsort(v_ids, kind="stable")
        ids = np.array(v_ids, dtype=np.int64)[order]
        undeclared = ~np.isin(e_ij, ids).all(axis=1)
        if undeclared.any():
            k = int(np.flatnonzero(undeclared)[0])
            raise InputFileError(f"{path}:{e_lines[k]}: edge ({e_ij[k, 0]}, {e_ij[k, 1]}) refers to an undeclared vertex")
        v_q, v_lines = [v_q[k] for k in order], [v_lines[k] for k in order]
    else:
        ids = np.unique(e_ij)
    try:  # vertices and edges together: one warning for the file
        q, _ = normalize_near_unit_quaternions(np.array(v_q + e_q).reshape(-1, 4), rotation_tol, source=str(path),
                                               labels=[f"of line {ln}" for ln in v_lines + e_lines])
    except NearRotationError as exc:
        raise InputFileError(str(exc)) from None
    qv, qe = q[: len(v_q)], q[len(v_q):]
    R_init = np.swapaxes(_from_xyzw(qv), 1, 2) if v_q else None  # cam_from_world = (world_from_cam)ᵀ
    Z = _from_xyzw(qe)                                  # T_i⁻¹T_j rotation = R̃_ijᵀ
    R_rel = np.swapaxes(Z, 1, 2)
    H = np.array(e_H)
    lam = np.linalg.eigvalsh(H)
    if np.any(lam[:, 0] <= 0):
        k = int(np.argmin(lam[:, 0]))
        raise InputFileError(f"{path}:{e_lines[k]}: the rotation information block is not positive definite "
                             f"(smallest eigenvalue {lam[k, 0]:.3g})")
    t = np.array(e_t)
    edges = np.searchsorted(ids, e_ij)  # ids are sorted and hold every endpoint
    # orient i < j: the reverse measurement is Z̃ᵀ with translation −Z̃ᵀ t; H maps to R̃ᵀ H R̃ (from_edges)
    flip = edges[:, 0] > edges[:, 1]
    t = np.where(flip[:, None], -np.einsum("mba,mb->ma", Z, t), t)
    try:
        vg = ViewGraph.from_edges([str(v) for v in ids], edges, R_rel, H=H, stats={"t_g2o": t}, allow_isolated=True)
    except ViewGraphError as exc:
        raise InputFileError(f"{path}: {exc}") from None
    return G2oData(vg, R_init, ids, dict(counts))
