"""A pycolmap incremental reconstruction of an image folder, used as a reference (a stage).

The reference answers "how far are our rotations from what a standard
incremental SfM gives on the same images". By default it runs pycolmap's own
SIFT extraction and exhaustive matching, so it does not depend on our front
end; ``use_our_matches`` instead imports our keypoints and matches from the
WORK folder of :mod:`pipeline.frontend.feature_stage` /
:mod:`pipeline.frontend.matching_stage` into the COLMAP database and lets pycolmap
verify and map them.

The image checks, the K handling, the database, the result files and the timing
are those of every pycolmap peer (:class:`pipeline.reference.peer.PeerStage`,
shared with the GLOMAP peer :mod:`pipeline.reference.global_mapping`): an image
pycolmap cannot safely decode (a PNG whose header claims 60000×60000 pixels would
make it abort) is left out with a warning and listed, with why, among the
unregistered images; a known K (``--K``, or the file the feature stage finds in
the image folder) is passed as fixed PINHOLE cameras, otherwise pycolmap uses EXIF
or its default focal (1.2·max(w, h)) and refines it.

Output folder layout (``OUT`` = the stage's folder)::

    OUT/database-<key>.db          COLMAP database (features + verified matches),
    OUT/database-<key>.times.json  reused while the images, K and database options
                                   are unchanged
    OUT/models-<key>/<k>/          every model pycolmap returned (COLMAP binary)
    OUT/model/, OUT/rotations.txt, OUT/reference.json   the result (pipeline.reference.models)
    OUT/reference.record.json      the stage record (pipeline.stage)

An interrupted run resumes from the last finished step (database, then
mapping); its temporaries carry :data:`pipeline.core.atomic.TMP_TAG` and the next
run removes them, and entries of other keys are removed when a run finishes.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.reference.peer import PeerConfig, PeerStage, known_intrinsics, peer_cli, run_peer

logger = logging.getLogger(__name__)

__all__ = ["ReferenceConfig", "IncrementalReferenceStage", "known_intrinsics", "main", "main_cli"]


@dataclass(frozen=True, kw_only=True)
class ReferenceConfig(PeerConfig):
    """Options of the pycolmap incremental reference (YAML section ``reference``)."""

    SECTION = "reference"


class IncrementalReferenceStage(PeerStage):
    """pycolmap's incremental reconstruction of an image folder, as a reference (see :class:`PeerStage`)."""

    name = "reference"
    title = "pycolmap reference"
    config_cls = ReferenceConfig
    mapping = "incremental mapping"

    def map(self, pc: Any, db_path: Path, out: Path) -> dict[int, Any]:
        """pycolmap's incremental mapping of the database into folder ``out``."""
        from tqdm import tqdm  # noqa: PLC0415

        opts = self.common_options(pc.IncrementalPipelineOptions())
        if self.fixed_intrinsics():
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
        with tqdm(total=len(self.scan()["given"]), desc="pycolmap mapping", unit="img",
                  disable=not self.progress) as bar:
            # the callback fires once per registered image (the first pair counts as two)
            return pc.incremental_mapping(db_path, self.images, out, options=opts,
                                          initial_image_pair_callback=lambda: bar.update(2),
                                          next_image_callback=lambda: bar.update(1))


def main(images: str | os.PathLike, out: str | os.PathLike, K: str | os.PathLike | np.ndarray | None = None,
         overwrite: bool = False, config: ReferenceConfig | None = None, work: str | os.PathLike | None = None,
         names: list[str] | None = None, progress: bool = True) -> Path:
    """Reconstruct ``images`` with pycolmap into ``out`` (resumable); returns ``out/reference.json``.

    Args:
        images: folder of images.
        out: output folder (created).
        K: known intrinsics (see :func:`known_intrinsics`), or None.
        overwrite: redo everything.
        config: options; defaults to ``ReferenceConfig()``.
        work: our front end's WORK folder (only for ``use_our_matches``).
        names: image file names to use (default: every image in the folder).
        progress: show progress bars.
    """
    return run_peer(IncrementalReferenceStage, images, out, K=K, overwrite=overwrite, config=config, work=work,
                    names=names, progress=progress)


def main_cli(argv: Sequence[str] | None = None) -> int:
    return peer_cli(IncrementalReferenceStage, "python -m pipeline.reference",
                    "pycolmap incremental reconstruction of an image folder (a reference)", argv)

