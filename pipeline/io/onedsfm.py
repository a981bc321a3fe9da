"""1DSfM datasets (Wilson & Snavely, ECCV 2014): reader, writer and a synthetic folder generator.

Layout and conventions, established from public sources (facts, no code copied):

* ``list.txt``: one image per line, ``<image path> [0 <focal px>]``; the line number (0-based)
  is the image's index everywhere else (SfM_Init README, "Other included files").
* ``cc.txt``: the indices of the largest connected component, one per line (SfM_Init README).
* ``EGs.txt``: one two-view model per line, ``<i> <j> <Rij (9, row-major)> <tij (3)>``. The
  SfM_Init README: "If Ri and Rj are the rotation matrices of cameras i and j (world-to-camera
  maps) then in the absence of noise Rij = Ri * Rj'", and "t is the position of camera j in
  camera i's coordinate system". So the file's ``R_ij`` is the **transpose** of this project's
  ``R_j R_iᵀ``.
* Bundler's camera looks down **−z** (y up); this project's (COLMAP/OpenCV) looks down +z.
  With ``F = diag(1, −1, −1)``: ``R_cv = F R_bundler``, ``t_cv = F t_bundler``. Theia's
  1DSfM reader (``theia/io/read_1dsfm.cc``) does exactly this to the EGs: it reads R
  transposed and applies ``bundler_to_theia · Rᵀ · bundler_to_theia`` with
  ``bundler_to_theia = diag(1, −1, −1)``, and ``position ← bundler_to_theia · position``.
  Hence, for an EG line (i, j, R, t):  ``R_ij(ours) = F Rᵀ F``, and ``F t`` is the direction of
  camera j's centre in camera i's OpenCV frame; the pipeline's translation (``x_j = R_ij x_i + t``,
  ``stats["t"]``, GLOMAP's cam2_from_cam1) is ``−R_ij F t``.
* ``gt_bundle.out``: a Bundler v0.3 file (``# Bundle file v0.3``; ``<num_cameras>
  <num_points>``; per camera ``f k1 k2`` then 3 rows of R then t; then the points). R is
  world-to-camera in Bundler's frame; a camera with f <= 0 or an all-zero R is not
  registered (Bundler's rule, also Theia's ``ReadBundlerFiles``: a camera with f <= 0 was not
  reconstructed; a zero R gives no rotation either). Camera k is image k of ``list.txt``; a
  bundle with more cameras than list.txt has images is refused. Truth in our convention: ``F R``
  (:mod:`pipeline.io.bundler` reads and writes it).

Reading restricts to ``cc.txt`` (when present) and drops EGs with an endpoint outside it
(counted in ``info``); the rotations go through the near-rotation projection (the files
print ~6–9 significant digits).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.atomic import TMP_TAG, atomic_dir, atomic_open
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.names import positions
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.bundler import BUNDLER_TO_CV, read_bundler, write_bundler
from pipeline.io.common import line_numbers as _numbers
from pipeline.io.common import repeated_pair
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, OneWarning

__all__ = ["OneDSfMData", "read_1dsfm", "write_1dsfm", "read_bundler", "write_bundler", "is_1dsfm_folder",
           "check_1dsfm_target", "BUNDLER_TO_CV"]

logger = logging.getLogger(__name__)



@dataclass
class OneDSfMData:
    """A 1DSfM dataset read into the project's conventions.

    Attributes:
        vg: view graph over the cameras of ``cc.txt`` (names: image paths from list.txt),
            ``stats["t"]``: (M, 3) unit translation of cam2_from_cam1 (``x_j = R_ij x_i + t``, the
            pipeline's convention), from the EGs' camera positions.
        index: (N,) list.txt index of each camera of ``vg``.
        focal: (N,) focal length from list.txt (NaN when absent).
        R_gt: (N, 3, 3) cam_from_world truth from gt_bundle.out (identity where missing) or None.
        gt_mask: (N,) True where gt_bundle.out registers the camera, or None.
        info: counts (EGs read, dropped outside cc, ...).
    """

    vg: ViewGraph
    index: np.ndarray
    focal: np.ndarray
    R_gt: np.ndarray | None
    gt_mask: np.ndarray | None
    info: dict[str, int] = field(default_factory=dict)


# ----------------------------------------------------------------------------- low level
def _read_text(path: Path, what: str) -> list[str]:
    if not path.is_file():
        raise InputFileError(f"1DSfM {what} file {path} does not exist")
    try:
        return path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path} is not a readable text file ({exc.__class__.__name__})") from None


def _read_list(path: Path) -> tuple[list[str], np.ndarray]:
    names, focal = [], []
    for lineno, line in enumerate(_read_text(path, "list"), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) not in (1, 3):
            raise InputFileError(f"{path}:{lineno}: expected '<image> [0 <focal>]' (1 or 3 fields), got {len(parts)}")
        names.append(parts[0])
        focal.append(_numbers(path, lineno, parts[2:3])[0] if len(parts) == 3 else np.nan)
    if not names:
        raise InputFileError(f"{path} lists no images")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputFileError(f"{path}: image names repeat: {dup[:3]}")
    return names, np.array(focal, dtype=np.float64)


def _read_cc(path: Path, n_images: int) -> np.ndarray:
    idx = []
    for lineno, line in enumerate(_read_text(path, "cc"), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 1:
            raise InputFileError(f"{path}:{lineno}: expected one image index per line, got {len(parts)} fields")
        v = _numbers(path, lineno, parts, float)[0]
        if v != int(v) or not 0 <= v < n_images:
            raise InputFileError(f"{path}:{lineno}: image index {parts[0]} is not in [0, {n_images}) of list.txt")
        idx.append(int(v))
    if not idx:
        raise InputFileError(f"{path} holds no image index")
    return np.unique(np.array(idx, dtype=np.int64))


def _read_egs(path: Path, n_images: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    ij, Rs, ts, lines = [], [], [], []
    for lineno, line in enumerate(_read_text(path, "EGs"), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 14:
            raise InputFileError(f"{path}:{lineno}: expected '<i> <j> <R 9 values> <t 3 values>' (14 fields), "
                                 f"got {len(parts)}")
        v = _numbers(path, lineno, parts)
        i, j = v[0], v[1]
        if i != int(i) or j != int(j) or not (0 <= i < n_images and 0 <= j < n_images):
            raise InputFileError(f"{path}:{lineno}: image indices ({parts[0]}, {parts[1]}) not in [0, {n_images})")
        if i == j:
            raise InputFileError(f"{path}:{lineno}: an EG of image {int(i)} with itself; delete the line")
        ij.append((int(i), int(j)))
        Rs.append(v[2:11])
        ts.append(v[11:14])
        lines.append(lineno)
    if not ij:
        raise InputFileError(f"{path} holds no EGs")
    return np.array(ij, np.int64), np.array(Rs).reshape(-1, 3, 3), np.array(ts), lines


def _check_camera_count(bundle: Path, n_cam: int, list_path: Path, n_img: int) -> None:
    if n_cam > n_img:  # camera k is image k: the files are not of one dataset
        raise InputFileError(f"{bundle} has {n_cam} cameras but {list_path} lists {n_img} images; camera k is image k "
                             "of list.txt: check that both files are of this dataset")


# ----------------------------------------------------------------------------- read / write
def read_1dsfm(folder: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL,
               use_cc: bool = True, read_truth: bool = True) -> OneDSfMData:
    """Read a 1DSfM folder (``list.txt``, ``EGs.txt``, optional ``cc.txt`` and ``gt_bundle.out``).

    Args:
        folder: the dataset folder.
        rotation_tol: near-rotation tolerance (``near_rotation``); the EG rotations are projected.
        use_cc: restrict to ``cc.txt`` (when present); else to the images with an EG.
        read_truth: read ``gt_bundle.out`` when present.

    Returns:
        :class:`OneDSfMData`.

    Raises:
        InputFileError: a missing required file, any malformed line (``file:line: ...``),
            EG rotations beyond the tolerance, a pair given twice.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(f"1DSfM folder {folder} does not exist")
    names, focal = _read_list(folder / "list.txt")
    n_img = len(names)
    ij, R_file, t_file, eg_lines = _read_egs(folder / "EGs.txt", n_img)
    cc_path = folder / "cc.txt"
    if use_cc and cc_path.is_file():
        cams = _read_cc(cc_path, n_img)
    else:
        cams = np.unique(ij)
    old_to_new = -np.ones(n_img, dtype=np.int64)
    old_to_new[cams] = np.arange(cams.size)
    keep = np.all(old_to_new[ij] >= 0, axis=1)
    info = {"n_images_listed": n_img, "n_cameras": int(cams.size), "n_egs": int(ij.shape[0]),
            "n_egs_outside_cc": int((~keep).sum())}
    if not keep.any():
        raise InputFileError(f"{folder / 'EGs.txt'}: none of its {ij.shape[0]} EGs joins two images of "
                             f"{folder / 'cc.txt'}; check that cc.txt is of this dataset (or delete it)")
    if info["n_egs_outside_cc"]:
        logger.warning("%s: %d of %d EGs have an image outside cc.txt; dropped", folder / "EGs.txt",
                       info["n_egs_outside_cc"], ij.shape[0])
    ij, R_file, t_file = ij[keep], R_file[keep], t_file[keep]
    lines = [ln for ln, k in zip(eg_lines, keep) if k]
    rep = repeated_pair(ij)
    if rep is not None:  # named as the file names it: list.txt indices and line numbers
        a, b = rep
        raise InputFileError(f"{folder / 'EGs.txt'}:{lines[b]}: images {ij[b, 0]} and {ij[b, 1]} already have an EG on "
                             f"line {lines[a]}; each pair may appear once, in either orientation: delete one of the lines")
    near = OneWarning(folder, rotation_tol)  # near-rotations of EGs.txt and gt_bundle.out: one warning for the dataset
    R_file = near.rotations(R_file, "EG rotation", [f"on line {ln}" for ln in lines], source=folder / "EGs.txt")
    F = BUNDLER_TO_CV
    R_rel = F @ np.swapaxes(R_file, 1, 2) @ F         # our R_j R_iᵀ for the file's (i, j)
    # the file's t is camera j's centre in camera i's frame; the pipeline's t (x_j = R_ij x_i + t) is −R_ij of it
    t_rel = -np.einsum("mab,mb->ma", R_rel, t_file @ F.T)
    nrm = np.linalg.norm(t_rel, axis=1, keepdims=True)
    t_rel = np.where(nrm > 0, t_rel / np.where(nrm > 0, nrm, 1.0), 0.0)
    e = old_to_new[ij]
    flip = e[:, 0] > e[:, 1]
    # an EG written with i > j is stored as (j, i): the inverse rigid transform, t_ji = −R_ijᵀ t_ij
    t_rel = np.where(flip[:, None], -np.einsum("mba,mb->ma", R_rel, t_rel), t_rel)
    try:
        vg = ViewGraph.from_edges([names[k] for k in cams], e, R_rel, stats={"t": t_rel}, allow_isolated=True)
    except ViewGraphError as exc:
        raise InputFileError(f"{folder / 'EGs.txt'}: {exc}") from None
    R_gt = gt_mask = None
    gt_path = folder / "gt_bundle.out"
    if read_truth and gt_path.is_file():
        Rb, _, _, reg = read_bundler(gt_path, rotation_tol, _near=near)
        _check_camera_count(gt_path, Rb.shape[0], folder / "list.txt", n_img)
        if Rb.shape[0] < n_img:
            logger.warning("%s has %d cameras for %d listed images; the rest count as unregistered",
                           gt_path, Rb.shape[0], n_img)
        R_all = np.broadcast_to(np.eye(3), (n_img, 3, 3)).copy()
        m_all = np.zeros(n_img, bool)
        k = min(n_img, Rb.shape[0])
        R_all[:k], m_all[:k] = Rb[:k], reg[:k]
        R_gt, gt_mask = R_all[cams], m_all[cams]
        info["n_gt_registered"] = int(gt_mask.sum())
    near.warn()
    return OneDSfMData(vg, cams, focal[cams], R_gt, gt_mask, info)


def write_1dsfm(folder: str | os.PathLike, vg: ViewGraph, *, list_names: list[str] | None = None,
                index: np.ndarray | None = None, focal: np.ndarray | None = None,
                R_gt: np.ndarray | None = None, t_gt: np.ndarray | None = None, gt_mask: np.ndarray | None = None
                ) -> Path:
    """Write a view graph as a 1DSfM folder (inverse of :func:`read_1dsfm`), atomically as a whole.

    Args:
        folder: created if needed; an existing one may hold only files this function writes (it is
            replaced whole, so no gt_bundle.out of an earlier dataset stays); else InputFileError.
        vg: the view graph; ``stats["t"]`` (cam2_from_cam1) written as the EGs' positions (0 if absent).
        list_names: all images of list.txt (default: ``vg.names``); may include images not in vg.
        index: (N,) list.txt index of each camera of vg (default: position of its name).
        focal: (len(list_names),) focal lengths, NaN = unknown (written without "0 f").
        R_gt, t_gt, gt_mask: (len(list_names), ...) truth for gt_bundle.out (optional).
    """
    folder = Path(folder)
    check_1dsfm_target(folder)
    with atomic_dir(folder) as tmp:  # the folder is replaced whole: no file of an earlier dataset stays beside
        _write_1dsfm_files(tmp, vg, list_names, index, focal, R_gt, t_gt, gt_mask)
    return folder


#: What :func:`write_1dsfm` writes (a folder holding only these, or nothing, may be replaced).
_WRITTEN = ("list.txt", "cc.txt", "EGs.txt", "gt_bundle.out")


def check_1dsfm_target(folder: str | os.PathLike) -> None:
    """Refuse (one line) a target that :func:`write_1dsfm` would mix up: a file, or a folder with other files."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputFileError(f"{folder} is a file; a 1DSfM dataset is a folder: give a folder name")
    if folder.is_dir():
        other = sorted(f.name for f in folder.iterdir() if f.name not in _WRITTEN and TMP_TAG not in f.name)
        if other:
            raise InputFileError(f"{folder} holds {', '.join(other[:3])}{' ...' if len(other) > 3 else ''}, which a "
                                 "1DSfM folder written there would not replace; give a new or empty folder")


def _write_1dsfm_files(folder: Path, vg: ViewGraph, list_names, index, focal, R_gt, t_gt, gt_mask) -> None:
    list_names = list(vg.names) if list_names is None else list(list_names)
    index = positions(list_names, vg.names) if index is None else np.asarray(index)
    focal = np.full(len(list_names), np.nan) if focal is None else np.asarray(focal, float)
    with atomic_open(folder / "list.txt") as fh:
        for n, f in zip(list_names, focal):
            fh.write(n + ("\n" if not np.isfinite(f) else f" 0 {f:.17g}\n"))
    with atomic_open(folder / "cc.txt") as fh:
        fh.write("".join(f"{k}\n" for k in np.sort(index)))
    F = BUNDLER_TO_CV
    R_file = F @ np.swapaxes(vg.R_rel, 1, 2) @ F     # inverse of the reader's F Rᵀ F
    t = np.asarray(vg.stats.get("t", np.zeros((vg.n_edges, 3))), float).reshape(vg.n_edges, 3)
    t = -np.einsum("mba,mb->ma", vg.R_rel, t) @ F.T   # camera j's centre in camera i's frame, Bundler's axes
    with atomic_open(folder / "EGs.txt") as fh:
        for (i, j), Rk, tk in zip(index[vg.edges], R_file, t):
            fh.write(f"{i} {j} " + " ".join(f"{x:.17g}" for x in (*Rk.ravel(), *tk)) + "\n")
    if R_gt is not None:
        K = len(list_names)
        t_gt = np.zeros((K, 3)) if t_gt is None else t_gt
        f_out = np.where(np.isfinite(focal), focal, 1000.0)
        write_bundler(folder / "gt_bundle.out", R_gt, t_gt, f_out, gt_mask)


def is_1dsfm_folder(path: str | os.PathLike) -> bool:
    """A folder holding ``EGs.txt`` and ``list.txt`` (the 1DSfM layout)."""
    p = Path(path)
    return p.is_dir() and (p / "EGs.txt").is_file() and (p / "list.txt").is_file()


def read_1dsfm_reference(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL
                         ) -> tuple[list[str], np.ndarray]:
    """The ground truth of a 1DSfM dataset as a reference: a folder or its ``gt_bundle.out``.

    Camera k of ``gt_bundle.out`` is image k of ``list.txt`` beside it; unregistered
    cameras are left out.

    Returns:
        names (list.txt paths) and (K, 3, 3) cam_from_world rotations.

    Raises:
        InputFileError: no ``list.txt`` beside the bundle file, or a malformed file.
    """
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    bundle = p if p.is_file() else folder / "gt_bundle.out"
    if not (folder / "list.txt").is_file():
        raise InputFileError(f"{bundle}: a Bundler file is a 1DSfM reference only with list.txt beside it (camera k "
                             f"is image k of list.txt); none in {folder}")
    names, _ = _read_list(folder / "list.txt")
    R, _, _, registered = read_bundler(bundle, rotation_tol)
    _check_camera_count(bundle, R.shape[0], folder / "list.txt", len(names))
    k = np.flatnonzero(registered)
    return [names[i] for i in k], R[k]
