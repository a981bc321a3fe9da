"""Every view-graph input a user may have, recognised by its name, extension or folder layout.

==========================================  ==============================================
input                                       read by
==========================================  ==============================================
``*.npz``                                   ``ViewGraph.load`` (ours)
``*.mat`` (LU Sphinx or ℓ1 layout)          :func:`pipeline.io.mat.read_mat`
a folder with ``EGs.txt`` and ``list.txt``  :func:`pipeline.io.onedsfm.read_1dsfm` (1DSfM;
(or its ``EGs.txt``)                        ``gt_bundle.out`` is its ground truth)
``*.g2o``                                   :func:`pipeline.io.g2o.read_g2o`
text, 9 fields a line                       :func:`pipeline.io.glomap.read_glomap_relpose`
                                            (GLOMAP's relative poses)
==========================================  ==============================================

Rotations within ``rotation_tol`` of SO(3) are projected with one warning per file,
beyond it refused (:mod:`pipeline.io.near_rotation`). Every malformed input is one
:class:`InputFileError` line naming the file. :func:`input_files` lists the files an
input consists of (for the averaging stage's fingerprint).
"""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.core.errors import InputFileError
from pipeline.core.names import split_fields
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.mat import MatData, read_mat
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL
from pipeline.io.onedsfm import is_1dsfm_folder, read_1dsfm

__all__ = ["read_input_graph", "check_input", "input_files", "can_hold_precisions", "GraphData", "FORMATS"]

#: One line per supported input, for messages and ``--help``.
FORMATS = ("a view-graph .npz (ViewGraph.save), a .mat (LU Sphinx or ℓ1 layout), a 1DSfM folder (EGs.txt, "
           "list.txt, cc.txt, gt_bundle.out), a .g2o file, or GLOMAP relative poses (NAME1 NAME2 QW QX QY QZ TX TY TZ)")

GraphData = MatData

#: The other files of a published 1DSfM folder: given alone, they are not a view graph.
_ONEDSFM_COMPANIONS = ("list.txt", "cc.txt", "gt_bundle.out", "coords.txt", "tracks.txt")


def _data_fields(path: Path) -> int:
    """Fields on the first non-comment line of a text file (0 if none); -1 if not text.

    Counted as our files write them (``"…"`` one name, ``#`` a comment) and, when that is no known
    layout (5, 9 or 10 fields), as GLOMAP writes them (whitespace only: ``IMG#12.jpg`` is a name).
    """
    try:
        with open(path, encoding="utf-8-sig") as f:
            for line in f:
                raw = line.split()
                if not raw or raw[0].startswith("#"):
                    continue
                try:
                    ours = len(split_fields(line))
                except InputFileError:
                    ours = -1
                return ours if ours in (5, 9, 10) or '"' in line else len(raw)
    except (OSError, UnicodeDecodeError):
        return -1
    return 0


def _folder_of(path: Path) -> Path | None:
    """The 1DSfM folder ``path`` names (the folder or its EGs.txt), or None."""
    if path.name == "EGs.txt" and is_1dsfm_folder(path.parent):
        return path.parent
    return path if is_1dsfm_folder(path) else None


def check_input(path: str | os.PathLike) -> None:
    """Refuse, in one line and before any work, an input that cannot be a view graph (missing, a plain folder, a
    companion file of a 1DSfM folder); :func:`read_input_graph` judges the content."""
    p = Path(path)
    if _folder_of(p) is not None:
        return
    egs = p / "EGs.txt" if p.is_dir() else p
    if egs.name == "EGs.txt" and egs.is_file() and not (egs.parent / "list.txt").is_file():
        raise InputFileError(f"{egs} is a 1DSfM EGs file, read with the list.txt beside it (line k names image k); "
                             f"none in {egs.parent}: put the dataset's list.txt there")
    if p.is_dir():
        inside = sorted(d.name for d in p.iterdir() if is_1dsfm_folder(d))  # the folder the 1DSfM archives unpack into
        if inside:
            raise InputFileError(f"{p} is a folder of 1DSfM datasets ({', '.join(inside[:5])}"
                                 f"{' ...' if len(inside) > 5 else ''}), not one; give one of them, e.g. {p / inside[0]}")
        raise InputFileError(f"{p} is a folder but not a 1DSfM dataset (EGs.txt and list.txt); expected {FORMATS}")
    if not p.exists():
        raise InputFileError(f"input view graph {p} does not exist")
    if p.name in _ONEDSFM_COMPANIONS and is_1dsfm_folder(p.parent):
        raise InputFileError(f"{p} is one file of the 1DSfM dataset in {p.parent}; give the folder {p.parent} (or its "
                             "EGs.txt)")


def can_hold_precisions(path: str | os.PathLike) -> bool:
    """Whether input ``path`` can carry H: an .npz, .mat or .g2o can; a 1DSfM folder or GLOMAP's text cannot."""
    p = Path(path)
    return _folder_of(p) is None and p.suffix.lower() in (".npz", ".mat", ".g2o")


def input_files(path: str | os.PathLike) -> list[Path]:
    """The files that make up input ``path`` (a 1DSfM folder is several), existing ones only."""
    p = Path(path)
    folder = _folder_of(p)
    if folder is not None:
        return [folder / n for n in ("list.txt", "EGs.txt", "cc.txt", "gt_bundle.out") if (folder / n).is_file()]
    return [p]


def read_input_graph(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL,
                     g2o_info: str = "gtsam") -> GraphData:
    """Read a view graph to average from any supported input (module docstring); ``g2o_info``: a ``.g2o``'s
    information convention (:func:`pipeline.io.g2o.read_g2o`'s ``info_convention``).

    Returns:
        :class:`GraphData` (``R_gt`` from a ``.mat``'s ``Rgt`` or a 1DSfM ``gt_bundle.out``,
        else None).

    Raises:
        InputFileError: a missing or unrecognised input, or malformed content (one line).
    """
    p = Path(path)
    folder = _folder_of(p)
    if folder is not None:
        d = read_1dsfm(folder, rotation_tol)
        return GraphData(d.vg, d.R_gt, d.gt_mask)
    check_input(p)
    suffix = p.suffix.lower()
    if suffix == ".npz":
        return GraphData(ViewGraph.load(p, allow_isolated=True), None, None)
    if suffix == ".mat":
        return read_mat(p, rotation_tol)
    if suffix == ".g2o":
        from pipeline.io.g2o import read_g2o  # noqa: PLC0415

        return GraphData(read_g2o(p, rotation_tol, info_convention=g2o_info).vg, None, None)
    nf = _data_fields(p)
    if nf == 9:
        from pipeline.io.glomap import read_glomap_relpose  # noqa: PLC0415

        return GraphData(read_glomap_relpose(p, rotation_tol), None, None)
    if nf == 0:
        raise InputFileError(f"{p} is empty (no data line); expected {FORMATS}")
    if nf in (5, 10):
        raise InputFileError(f"{p} holds rotations, not a view graph ({nf} fields a line: "
                             f"{'NAME QW QX QY QZ' if nf == 5 else 'name r11 ... r33'}); give it as --init, or to "
                             f"python -m pipeline.evaluate --rotations; the view graph is one of: {FORMATS}")
    raise InputFileError(f"{p}: unsupported view-graph input" + (f" ({nf} fields a line)" if nf > 0 else "")
                         + f"; expected {FORMATS}")
