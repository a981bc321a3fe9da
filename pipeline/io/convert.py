"""``python -m pipeline.convert``: a view graph or rotations from one tool's file format to another's.

Usage::

    python -m pipeline.convert INPUT OUTPUT [--to FORMAT] [--rotation-tol T] [--g2o-info gtsam|g2o]

INPUT is any view graph of :mod:`pipeline.io.graphs` (``.npz``, ``.mat``, a 1DSfM
folder, ``.g2o``, GLOMAP relative poses) or a rotations file (ours or GLOMAP's).
FORMAT (default: from OUTPUT's extension; ``.txt`` needs it):

=====================  ===========================================================
``npz``                our view graph (``ViewGraph.save``)
``mat``                the ℓ1 layout (``RR``, ``I``, ``Rgt`` when known, ``H``)
``1dsfm``              a 1DSfM folder (``list.txt``, ``cc.txt``, ``EGs.txt``,
                       ``gt_bundle.out`` when the truth is known)
``g2o``                ``EDGE_SE3:QUAT`` lines with H as the rotation information
                       (GTSAM's reading; ``VERTEX_SE3:QUAT`` from ``--rotations``;
                       ``--g2o-info g2o``: g2o's own, 4H, for a g2o INPUT too)
``glomap-relpose``     GLOMAP's ``NAME1 NAME2 QW QX QY QZ TX TY TZ``
``glomap-rotations``   GLOMAP's ``NAME QW QX QY QZ`` (from a rotations INPUT)
``rotations``          ours, ``name r11 … r33`` (from a rotations INPUT)
=====================  ===========================================================

Every output is written atomically (a 1DSfM folder as a whole). Before the input is read, an
OUTPUT that is the input, a folder where a file goes (or a file where a folder goes), or a 1DSfM
folder holding files this writer does not write is refused in one line; one warning names what
of the input the target cannot hold (camera names in ``.g2o``/``.mat``, H, the ground truth).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from pipeline.core.cli import run_cli
from pipeline.core.errors import ConfigError, InputFileError
from pipeline.io.graphs import FORMATS, read_input_graph
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL

__all__ = ["main", "main_cli", "TARGETS"]

TARGETS = ("npz", "mat", "1dsfm", "g2o", "glomap-relpose", "glomap-rotations", "rotations")
logger = logging.getLogger(__name__)
_BY_SUFFIX = {".npz": "npz", ".mat": "mat", ".g2o": "g2o", "": "1dsfm"}


def _is_rotations(path: Path) -> bool:
    from pipeline.io.graphs import _data_fields  # noqa: PLC0415

    return path.is_file() and path.suffix.lower() not in (".npz", ".mat", ".g2o") and _data_fields(path) in (5, 10)


_SUFFIX = {"npz": ".npz", "mat": ".mat", "g2o": ".g2o"}


def _check_output(src: Path, out: Path, fmt: str) -> None:
    """Refuse, before reading the input, an output that is the input or a folder where a file goes (and back)."""
    from pipeline.io.graphs import _folder_of  # noqa: PLC0415

    if out.resolve() in (src.resolve(), (_folder_of(src) or src).resolve()):
        raise ConfigError(f"OUTPUT {out} is the input; write the conversion to another path")
    blocked = next((d for d in out.parents if d.exists() and not d.is_dir()), None)
    if blocked is not None:
        raise InputFileError(f"{blocked} is a file, so {out} cannot be written in it; give another path")
    if fmt == "1dsfm":
        from pipeline.io.onedsfm import check_1dsfm_target  # noqa: PLC0415

        check_1dsfm_target(out)
    elif out.is_dir():
        raise InputFileError(f"{out} is a folder; --to {fmt} writes a file: pass a file name in it (e.g. "
                             f"{out / ('graph' + _SUFFIX.get(fmt, '.txt'))})")


def _warn_lost(data, out: Path, fmt: str) -> None:
    """One warning naming what of the input the target format cannot hold (names, H, the truth)."""
    vg, lost = data.vg, []
    if fmt in ("g2o", "mat") and list(vg.names) != [str(k) for k in range(vg.n_cameras)]:
        lost.append(f"camera names (camera k becomes {'vertex' if fmt == 'g2o' else 'index'} "
                    f"{'k' if fmt == 'g2o' else 'k+1'}: {vg.names[0]!r} is {0 if fmt == 'g2o' else 1})")
    if fmt in ("glomap-relpose", "1dsfm") and vg.H is not None:
        lost.append("precisions H")
    if fmt in ("npz", "g2o", "glomap-relpose") and data.R_gt is not None:
        lost.append("ground truth")
    if lost:
        logger.warning("%s (%s) cannot hold the input's %s; written without", out, fmt, " and ".join(lost))


def _vertex_rotations(path: Path, vg, rotation_tol: float) -> np.ndarray:
    """(N, 3, 3) rotations of ``path`` for the cameras of ``vg`` (matched by name, as ``--init``)."""
    from pipeline.io.rotations import rotations_for  # noqa: PLC0415

    return rotations_for(path, list(vg.names), f"--rotations {path} lacks rotations",
                         "give every camera of the view graph, or drop --rotations (vertices at identity)",
                         rotation_tol)


def main(input_path: str | Path, output: str | Path, to: str | None = None, rotations: str | Path | None = None,
         rotation_tol: float = DEFAULT_ROTATION_TOL, g2o_info: str = "gtsam") -> Path:
    """Convert ``input_path`` to ``output`` in format ``to`` (module docstring); returns ``output``.

    ``g2o_info``: the information convention of a ``.g2o`` read or written (``gtsam``: the block is H, as GTSAM
    reads it; ``g2o``: 4H, as g2o's own SE3 edges weigh the quaternion's vector part)."""
    src, out = Path(input_path), Path(output)
    fmt = to or _BY_SUFFIX.get(out.suffix.lower())
    if fmt not in TARGETS:
        raise ConfigError(f"cannot tell the format of {out} from its name; give --to with one of {list(TARGETS)}")
    _check_output(src, out, fmt)
    if rotations is not None and fmt != "g2o":
        raise ConfigError(f"--rotations is for --to g2o (its vertices); drop it for --to {fmt}")
    if rotations is not None and not Path(rotations).is_file():
        raise InputFileError(f"--rotations {rotations} is not a rotations file (missing, or a folder); give the file "
                             "of rotations for the g2o vertices")
    if _is_rotations(src):
        from pipeline.io.glomap import write_glomap_rotations  # noqa: PLC0415
        from pipeline.io.rotations import read_rotations, write_rotations  # noqa: PLC0415

        names, R = read_rotations(src, rotation_tol)
        if fmt == "glomap-rotations":
            return write_glomap_rotations(out, names, R)
        if fmt == "rotations":
            return write_rotations(out, names, R, header=f"converted from {src.name}")
        raise ConfigError(f"{src} holds rotations, not a view graph: --to glomap-rotations or rotations")
    if fmt in ("glomap-rotations", "rotations"):
        raise ConfigError(f"--to {fmt} needs a rotations file as INPUT; {src} is not one (10 or 5 fields a line)")
    data = read_input_graph(src, rotation_tol, g2o_info)
    vg = data.vg
    R0 = None if rotations is None else _vertex_rotations(Path(rotations), vg, rotation_tol)  # checked before writing
    _warn_lost(data, out, fmt)
    if fmt == "npz":
        return vg.save(out)
    if fmt == "mat":
        from pipeline.io.mat import write_l1_mat  # noqa: PLC0415

        R_gt = None if data.R_gt is None else np.where(data.gt_mask[:, None, None], data.R_gt, np.nan)
        return write_l1_mat(out, vg, R_gt=R_gt)
    if fmt == "1dsfm":
        from pipeline.io.onedsfm import write_1dsfm  # noqa: PLC0415

        return write_1dsfm(out, vg, R_gt=data.R_gt, gt_mask=data.gt_mask)
    if fmt == "g2o":
        from pipeline.io.g2o import write_g2o  # noqa: PLC0415

        return write_g2o(out, vg, R0, info_convention=g2o_info)
    from pipeline.io.glomap import write_glomap_relpose  # noqa: PLC0415

    return write_glomap_relpose(out, vg)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m pipeline.convert",
                                description="Convert a view graph or rotations between file formats.")
    p.add_argument("input", type=Path, help=f"{FORMATS}; or a rotations file (ours or GLOMAP's)")
    p.add_argument("output", type=Path, help="the file (or folder, for 1DSfM) to write")
    p.add_argument("--to", choices=TARGETS, default=None, help="output format (default: from OUTPUT's extension)")
    p.add_argument("--rotations", type=Path, default=None, help="g2o: rotations file for the vertices")
    p.add_argument("--rotation-tol", type=float, default=DEFAULT_ROTATION_TOL, metavar="T",
                   help=f"project input rotations within T of SO(3), refuse beyond (default {DEFAULT_ROTATION_TOL:g})")
    p.add_argument("--g2o-info", choices=("gtsam", "g2o"), default="gtsam",
                   help="information convention of a .g2o read or written: gtsam (the block is H, GTSAM's reading; "
                        "default) or g2o (4H, g2o's own SE3 edges)")
    return p


def main_cli(argv: list[str] | None = None) -> int:
    def body(a: argparse.Namespace) -> int:
        if not a.input.exists():
            raise InputFileError(f"input {a.input} does not exist")
        print(main(a.input, a.output, a.to, a.rotations, a.rotation_tol, a.g2o_info))
        return 0

    return run_cli(body, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main_cli())
