"""The view graph: named cameras, relative rotations, and optional precisions.

Conventions (``docs/CONVENTIONS.md``): edge ``k = (i, j)`` with ``i < j`` carries
``R_ij = R_j R_iᵀ`` (cam_from_world ``R``); the optional precision ``H_ij`` (1/rad²)
is that of ``Δω`` in ``R_j R_iᵀ = exp([Δω]×) R̃_ij``.

File format (``.npz``, written atomically, ``format_version`` 1):

====================  ==========  ================================================
key                   shape       meaning
====================  ==========  ================================================
``format``            ()          the string ``"rotavg-viewgraph"``
``format_version``    ()          1
``names``             (N,)        camera names (unicode)
``edges``             (M, 2)      int64 camera indices, ``i < j``
``R_rel``             (M, 3, 3)   ``R_ij = R_j R_iᵀ``
``H``                 (M, 3, 3)   precision of ``Δω``, 1/rad² (optional)
``inliers``           (M,)        int64 inlier counts (optional)
``stat__<name>``      (M, ...)    per-edge two-view statistics (optional)
====================  ==========  ================================================
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from pipeline.core import so3
from pipeline.core.atomic import save_npz
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.readers import read_npz

__all__ = ["ViewGraph", "Restriction", "precision_problem", "pair_keys"]

FORMAT = "rotavg-viewgraph"
FORMAT_VERSION = 1
ROTATION_TOL = 1e-6


def pair_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """One integer per unordered image pair (either order): ``min(a, b)·n + max(a, b)`` for N = ``n`` images."""
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    return np.minimum(a, b) * n + np.maximum(a, b)


def precision_problem(H: np.ndarray) -> tuple[int, str] | None:
    """The first of the (M, 3, 3) matrices ``H`` that is not a precision (finite, symmetric to 1e-8 relative,
    positive definite) and what is wrong with it (``"has NaN or inf"``, ...); None when every one is."""
    if not np.all(np.isfinite(H)):
        return int(np.flatnonzero(~np.isfinite(H).all(axis=(1, 2)))[0]), "has NaN or inf"
    scale = np.maximum(np.abs(H).max(axis=(1, 2)), 1e-300)
    asym = np.abs(H - np.swapaxes(H, 1, 2)).max(axis=(1, 2)) / scale
    if np.any(asym > 1e-8):
        k = int(np.argmax(asym))
        return k, (f"is not symmetric (relative asymmetry {asym[k]:.3g}); H must be a symmetric positive-definite "
                   "precision")
    with np.errstate(all="ignore"):  # entries near the float limit overflow: not a precision either
        lam = np.linalg.eigvalsh(0.5 * (H + np.swapaxes(H, 1, 2)))
    bad = ~(lam[:, 0] > 0) | ~np.isfinite(lam).all(axis=1)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        return k, f"is not positive definite (smallest eigenvalue {lam[k, 0]:.3g}); H must be a precision in 1/rad²"
    return None


@dataclass
class Restriction:
    """Index maps of a restriction to a subset of cameras.

    Attributes:
        kept: (n_new,) old camera index of each new camera.
        old_to_new: (n_old,) new index of each old camera, or -1 if dropped.
        edge_kept: (m_new,) old edge index of each new edge.
        dropped_names: names of the cameras left out.
    """

    kept: np.ndarray
    old_to_new: np.ndarray
    edge_kept: np.ndarray
    dropped_names: list[str]


@dataclass
class ViewGraph:
    """Cameras and pairwise relative rotations, validated on construction.

    Attributes:
        names: N camera names.
        edges: (M, 2) int camera indices with ``i < j``.
        R_rel: (M, 3, 3) measured ``R_ij ≈ R_j R_iᵀ``.
        H: (M, 3, 3) symmetric positive-definite precisions (1/rad²) or None.
        inliers: (M,) inlier counts or None.
        stats: per-edge arrays of leading size M (two-view statistics).
    """

    names: list[str]
    edges: np.ndarray
    R_rel: np.ndarray
    H: np.ndarray | None = None
    inliers: np.ndarray | None = None
    stats: dict[str, np.ndarray] = field(default_factory=dict)
    allow_isolated: bool = False

    def __post_init__(self) -> None:
        self.names = [str(n) for n in self.names]
        self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
        self.R_rel = np.asarray(self.R_rel, dtype=np.float64).reshape(-1, 3, 3)
        if self.H is not None:
            self.H = np.asarray(self.H, dtype=np.float64)
        if self.inliers is not None:
            self.inliers = np.asarray(self.inliers)
        self.stats = {k: np.asarray(v) for k, v in (self.stats or {}).items()}
        self.validate(allow_isolated=self.allow_isolated)

    # ------------------------------------------------------------------ basics
    @property
    def n_cameras(self) -> int:
        return len(self.names)

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    @property
    def has_H(self) -> bool:
        return self.H is not None

    def degrees(self) -> np.ndarray:
        """(N,) number of edges at each camera."""
        return np.bincount(self.edges.ravel(), minlength=self.n_cameras)

    # -------------------------------------------------------------- validation
    def validate(self, allow_isolated: bool = False) -> None:
        """Check every invariant; raise :class:`ViewGraphError` naming the first broken one.

        Args:
            allow_isolated: accept cameras with no edge (they are still reported
                by :meth:`components`).
        """
        N, M = self.n_cameras, self.n_edges
        if len(set(self.names)) != N:
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ViewGraphError(f"camera names must be unique; repeated: {dup[:5]}")
        if self.R_rel.shape != (M, 3, 3):
            raise ViewGraphError(f"R_rel.shape={self.R_rel.shape} but expected ({M}, 3, 3) for {M} edges")
        if M and (self.edges.min() < 0 or self.edges.max() >= N):
            k = int(np.flatnonzero((self.edges < 0).any(1) | (self.edges >= N).any(1))[0])
            raise ViewGraphError(
                f"edge {k} {tuple(self.edges[k].tolist())} has a camera index out of range [0, {N}); "
                "check the camera list and the edge indices (0-based)"
            )
        self_edges = np.flatnonzero(self.edges[:, 0] == self.edges[:, 1])
        if self_edges.size:
            k = int(self_edges[0])
            raise ViewGraphError(f"edge {k} is a self-edge ({self.edges[k, 0]}, {self.edges[k, 0]}); remove it")
        if M and np.any(self.edges[:, 0] > self.edges[:, 1]):
            k = int(np.flatnonzero(self.edges[:, 0] > self.edges[:, 1])[0])
            raise ViewGraphError(
                f"edge {k} {tuple(self.edges[k].tolist())} is not stored with i < j; "
                "use ViewGraph.from_edges to orient edges and invert their rotations"
            )
        if M:
            key = self.edges[:, 0] * N + self.edges[:, 1]
            uniq, counts = np.unique(key, return_counts=True)
            if np.any(counts > 1):
                d = int(uniq[np.argmax(counts > 1)])
                raise ViewGraphError(
                    f"duplicate edge ({d // N}, {d % N}): each camera pair may appear once, "
                    "in either orientation"
                )
        if not np.all(np.isfinite(self.R_rel)):
            k = int(np.flatnonzero(~np.isfinite(self.R_rel).all(axis=(1, 2)))[0])
            raise ViewGraphError(f"R_rel of edge {k} {tuple(self.edges[k].tolist())} has NaN or inf")
        ok = so3.is_rotation(self.R_rel, ROTATION_TOL)
        if not np.all(ok):
            k = int(np.flatnonzero(~ok)[0])
            R = self.R_rel[k]
            with np.errstate(all="ignore"):
                det, dev = np.linalg.det(R), np.abs(R.T @ R - np.eye(3)).max()
            raise ViewGraphError(
                f"R_rel of edge {k} {tuple(self.edges[k].tolist())} is not a rotation "
                f"(det={det:.6g}, max|RᵀR−I|={dev:.3g}, "
                f"tolerance {ROTATION_TOL}); project it with so3.project_to_so3"
            )
        if self.H is not None:
            if self.H.shape != (M, 3, 3):
                raise ViewGraphError(f"H.shape={self.H.shape} but expected ({M}, 3, 3)")
            problem = precision_problem(self.H)
            if problem is not None:
                k, what = problem
                raise ViewGraphError(f"H of edge {k} {tuple(self.edges[k].tolist())} {what}")
        if self.inliers is not None and self.inliers.shape != (M,):
            raise ViewGraphError(f"inliers.shape={self.inliers.shape} but expected ({M},)")
        for name, arr in self.stats.items():
            if arr.shape[:1] != (M,):
                raise ViewGraphError(f"stats[{name!r}].shape={arr.shape} but expected leading size {M}")
        if not allow_isolated:
            iso = np.flatnonzero(self.degrees() == 0)
            if iso.size:
                names = [self.names[i] for i in iso[:5]]
                raise ViewGraphError(
                    f"{iso.size} camera(s) have no edge, e.g. {names}; remove them or "
                    "restrict to the largest connected component"
                )

    # ------------------------------------------------------------ construction
    @classmethod
    def from_edges(
        cls,
        names: list[str],
        edges: np.ndarray,
        R_rel: np.ndarray,
        H: np.ndarray | None = None,
        inliers: np.ndarray | None = None,
        stats: dict[str, np.ndarray] | None = None,
        allow_isolated: bool = False,
    ) -> "ViewGraph":
        """Build a view graph from edges in any orientation.

        An edge ``(j, i)`` with ``j > i`` carrying ``R_ji`` is stored as ``(i, j)``
        with ``R_ij = R_jiᵀ``. Its precision becomes ``R_jiᵀ H R_ji`` because
        ``R_i R_jᵀ = exp([Δω]×) R̃`` implies ``R_j R_iᵀ = exp([−R̃ᵀΔω]×) R̃ᵀ``.
        Edges are then sorted by ``(i, j)``.
        """
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2).copy()
        R_rel = np.asarray(R_rel, dtype=np.float64).reshape(-1, 3, 3).copy()
        flip = edges[:, 0] > edges[:, 1]
        edges[flip] = edges[flip][:, ::-1]
        if H is not None:
            H = np.asarray(H, dtype=np.float64).copy()
            if H.shape == R_rel.shape:
                H[flip] = np.swapaxes(R_rel[flip], 1, 2) @ H[flip] @ R_rel[flip]
        R_rel[flip] = np.swapaxes(R_rel[flip], 1, 2)
        order = np.lexsort((edges[:, 1], edges[:, 0]))
        pick = (lambda a: None if a is None else np.asarray(a)[order])
        return cls(
            names=list(names),
            edges=edges[order],
            R_rel=R_rel[order],
            H=pick(H),
            inliers=pick(inliers),
            stats={k: np.asarray(v)[order] for k, v in (stats or {}).items()},
            allow_isolated=allow_isolated,
        )

    @classmethod
    def from_absolute(cls, names: list[str], R: np.ndarray, edges: np.ndarray, **kw) -> "ViewGraph":
        """Noise-free view graph ``R_ij = R_j R_iᵀ`` from absolute rotations ``R`` (N, 3, 3)."""
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        return cls.from_edges(names, edges, so3.relative(R, edges), **kw)

    # ------------------------------------------------------------------ graphs
    def adjacency(self, weights: np.ndarray | None = None) -> sp.csr_matrix:
        """(N, N) symmetric sparse adjacency, with ``weights`` (M,) or ones."""
        w = np.ones(self.n_edges) if weights is None else np.asarray(weights, float)
        i, j = self.edges.T
        A = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(self.n_cameras,) * 2)
        return A.tocsr()

    def incidence(self) -> sp.csr_matrix:
        """(M, N) incidence matrix with −1 at ``i`` and +1 at ``j`` for each edge."""
        M = self.n_edges
        rows = np.repeat(np.arange(M), 2)
        cols = self.edges.ravel()
        vals = np.tile([-1.0, 1.0], M)
        return sp.csr_matrix((vals, (rows, cols)), shape=(M, self.n_cameras))

    def components(self) -> np.ndarray:
        """(N,) component label of each camera; label 0 is the largest component."""
        _, labels = connected_components(self.adjacency(), directed=False)
        sizes = np.bincount(labels)
        order = np.argsort(-sizes, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return rank[labels]

    def is_connected(self) -> bool:
        return bool(self.n_cameras > 0 and np.all(self.components() == 0))

    def subgraph(self, keep: np.ndarray) -> tuple["ViewGraph", Restriction]:
        """Restrict to the cameras ``keep`` (indices or a boolean mask) and the edges among them."""
        keep = np.asarray(keep)
        if keep.dtype == bool:
            keep = np.flatnonzero(keep)
        keep = np.unique(keep)
        old_to_new = -np.ones(self.n_cameras, dtype=np.int64)
        old_to_new[keep] = np.arange(keep.size)
        e_keep = np.flatnonzero((old_to_new[self.edges] >= 0).all(axis=1))
        sub = ViewGraph(
            names=[self.names[i] for i in keep],
            edges=old_to_new[self.edges[e_keep]],
            R_rel=self.R_rel[e_keep],
            H=None if self.H is None else self.H[e_keep],
            inliers=None if self.inliers is None else self.inliers[e_keep],
            stats={k: v[e_keep] for k, v in self.stats.items()},
            allow_isolated=True,
        )
        dropped = [self.names[i] for i in np.flatnonzero(old_to_new < 0)]
        return sub, Restriction(keep, old_to_new, e_keep, dropped)

    def largest_component(self) -> tuple["ViewGraph", Restriction]:
        """Restrict to the largest connected component, with index maps both ways."""
        return self.subgraph(self.components() == 0)

    def with_H(self, H: np.ndarray | None) -> "ViewGraph":
        """A copy with the precisions replaced."""
        return ViewGraph(self.names, self.edges, self.R_rel, H, self.inliers, dict(self.stats), self.allow_isolated)

    # --------------------------------------------------------------------- I/O
    def save(self, path: str | os.PathLike) -> Path:
        """Write the documented ``.npz`` format atomically."""
        arrays: dict[str, np.ndarray] = {
            "format": np.array(FORMAT),
            "format_version": np.array(FORMAT_VERSION),
            "names": np.array(self.names, dtype=str),
            "edges": self.edges,
            "R_rel": self.R_rel,
        }
        if self.H is not None:
            arrays["H"] = self.H
        if self.inliers is not None:
            arrays["inliers"] = self.inliers
        for k, v in self.stats.items():
            arrays[f"stat__{k}"] = v
        return save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike, allow_isolated: bool = False) -> "ViewGraph":
        """Read a file written by :meth:`save`.

        Raises:
            InputFileError: a missing, unreadable or foreign file, or arrays of the wrong shape or type
                (one line naming the file).
            ViewGraphError: arrays that break an invariant of the graph (naming the file).
        """
        path = Path(path)
        data = read_npz(path, "view-graph .npz file", InputFileError)
        if "format" not in data or data["format"].shape != () or str(data["format"]) != FORMAT:
            raise InputFileError(f"{path} is not a view-graph file (missing format tag {FORMAT!r})")
        if "format_version" not in data:
            raise InputFileError(f"{path} lacks the array 'format_version'; re-run the stage that wrote it")
        fv = data["format_version"]
        if fv.shape != () or fv.dtype.kind not in "iu":
            raise InputFileError(f"{path}: format_version has shape {fv.shape} and dtype {fv.dtype}, expected one "
                                 "integer; re-run the stage that wrote it")
        if int(fv) > FORMAT_VERSION:
            raise InputFileError(f"{path} has format_version {int(fv)}; this code reads <= {FORMAT_VERSION}")
        for key in ("names", "edges", "R_rel"):
            if key not in data:
                raise InputFileError(f"{path} lacks the array {key!r}")
        # (trailing shape, kinds, what): the leading sizes are checked against each other by validate()
        layout = {"names": ((), "U", "a list of names"), "edges": ((2,), "iu", "(M, 2) integer camera indices"),
                  "R_rel": ((3, 3), "fiu", "(M, 3, 3) rotations"), "H": ((3, 3), "fiu", "(M, 3, 3) precisions"),
                  "inliers": ((), "iu", "(M,) integer counts")}
        for key, (tail, kinds, what) in layout.items():
            a = data.get(key)
            if a is not None and (a.ndim != 1 + len(tail) or a.shape[1:] != tail or a.dtype.kind not in kinds):
                raise InputFileError(f"{path}: {key} has shape {a.shape} and dtype {a.dtype}, expected {what}; "
                                     "re-run the stage that wrote it")
        stats = {k[len("stat__"):]: v for k, v in data.items() if k.startswith("stat__")}
        for key, a in stats.items():
            if a.dtype.kind not in "biuf":
                raise InputFileError(f"{path}: stat {key!r} has dtype {a.dtype}, expected numbers")
        try:
            return cls(names=[str(n) for n in data["names"]], edges=data["edges"], R_rel=data["R_rel"],
                       H=data.get("H"), inliers=data.get("inliers"), stats=stats, allow_isolated=allow_isolated)
        except ViewGraphError as exc:
            raise ViewGraphError(f"{path}: {exc}") from None
