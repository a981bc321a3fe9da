"""pycolmap's global SfM (GLOMAP, ``pycolmap.global_mapping``) of an image folder, as a peer (a stage).

The second pycolmap peer, beside the incremental reference
(:mod:`pipeline.reference.incremental`): GLOMAP's rotation averaging, global
positioning, bundle adjustment and retriangulation in one call. Everything but the
mapping call is shared with the incremental peer (:class:`pipeline.reference.peer.PeerStage`):
the same image checks, the same K handling (a known K is passed as fixed PINHOLE
cameras and kept constant in bundle adjustment), the same database (shared with
the incremental peer when both are given the same ``database_dir``: the mappers
read it and never write it), the same result files and the same timing
(extraction + matching + mapping).

Output folder layout (``OUT`` = the stage's folder, ``OUT/reference-global`` in ``run.py``)::

    OUT/models-<key>/<k>/      every model pycolmap returned (COLMAP binary)
    OUT/model/, OUT/rotations.txt, OUT/reference.json   the result (pipeline.reference.models)
    OUT/global_reference.record.json                     the stage record

Command line::

    python -m pipeline.reference.global_mapping --images DIR --out OUT [--K FILE] [--database-dir DIR]
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.reference.database import DatabaseConfig
from pipeline.reference.models import load_reference
from pipeline.reference.peer import PeerConfig, PeerStage, peer_cli, run_peer
from pipeline.reference.types import Reference

__all__ = ["GlobalReferenceConfig", "GlobalReferenceStage", "LABEL", "main", "main_cli", "load_global_reference"]

#: The label of the GLOMAP peer in metrics and reports.
LABEL = "glomap"


@dataclass(frozen=True, kw_only=True)
class GlobalReferenceConfig(PeerConfig):
    """Options of the pycolmap global (GLOMAP) peer (YAML section ``global_reference``)."""

    SECTION = "global_reference"

    @classmethod
    def sharing_database(cls, database: DatabaseConfig, options: dict[str, Any] | None = None
                         ) -> "GlobalReferenceConfig":
        """The config with the database options of ``database`` (the incremental peer's), so both map one database.

        Args:
            database: the config whose database options to take.
            options: this peer's own YAML section (mapping options; database keys given here win).
        """
        shared = {f.name: getattr(database, f.name) for f in fields(DatabaseConfig)}
        return cls.from_dict({**shared, **(options or {})}, where=f"[{cls.SECTION}]")


class GlobalReferenceStage(PeerStage):
    """pycolmap's global SfM (GLOMAP) of an image folder, as a peer (see :class:`PeerStage`)."""

    name = "global_reference"
    title = "pycolmap global (GLOMAP)"
    config_cls = GlobalReferenceConfig
    mapping = "global mapping (GLOMAP)"

    def map(self, pc: Any, db_path: Path, out: Path) -> dict[int, Any]:
        """``pycolmap.global_mapping`` of the database into folder ``out``."""
        opts = self.common_options(pc.GlobalPipelineOptions())
        if not getattr(pc, "has_cuda", False):  # a CPU build: its solvers are used either way, without two warnings
            opts.mapper.global_positioning.use_gpu = False
            opts.mapper.bundle_adjustment.ceres.use_gpu = False
        if self.fixed_intrinsics():
            ba = opts.mapper.bundle_adjustment  # a reference: the assignments stick
            ba.refine_focal_length = False
            ba.refine_principal_point = False
            ba.refine_extra_params = False
        return pc.global_mapping(db_path, self.images, out, opts)


def main(images: str | os.PathLike, out: str | os.PathLike, K: str | os.PathLike | np.ndarray | None = None,
         overwrite: bool = False, config: GlobalReferenceConfig | None = None, work: str | os.PathLike | None = None,
         names: list[str] | None = None, progress: bool = True, database_dir: str | os.PathLike | None = None) -> Path:
    """Reconstruct ``images`` with GLOMAP into ``out`` (resumable); returns ``out/reference.json``.

    Args: as :func:`pipeline.reference.incremental.main`, and ``database_dir``: the folder of a
    COLMAP database to share (the incremental peer's ``OUT``; default ``out``).
    """
    return run_peer(GlobalReferenceStage, images, out, K=K, overwrite=overwrite, config=config, work=work,
                    names=names, progress=progress, database_dir=database_dir)


def load_global_reference(out: str | Path) -> Reference:
    """The GLOMAP peer written in ``out``, labelled :data:`LABEL`."""
    return load_reference(out, label=LABEL)


def main_cli(argv: Sequence[str] | None = None) -> int:
    return peer_cli(GlobalReferenceStage, "python -m pipeline.reference.global_mapping",
                    "pycolmap global SfM (GLOMAP) of an image folder (a peer)", argv)


if __name__ == "__main__":
    sys.exit(main_cli())
