"""The one reference type: cameras to evaluate against, whatever their source.

A :class:`Reference` comes from a truth reader (:func:`pipeline.reference.truth.read_reference`:
a cameras file, Strecha ``gt_dense_cameras/``, Middlebury ``*_par.txt``, a COLMAP
model, a rotations file, a ``.mat`` with ``Rgt``), from a reconstruction made here
(:func:`pipeline.reference.incremental.load_reference`: pycolmap's registered
images, with why each other image is missing), or from restricting another
reference to a subset of its images (:meth:`Reference.subset`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import KW_ONLY, dataclass, field
from typing import Any

import numpy as np

__all__ = ["Reference"]


@dataclass(frozen=True, eq=False)
class Reference:
    """Reference cameras.

    Attributes:
        names: N camera (image) names.
        cam_from_world: (N, 3, 3) rotations, ``x_cam = R X + t``.
        centers: (N, 3) camera centres in world coordinates, when known.
        K: (N, 3, 3) intrinsics, when the source has them.
        source: the format or producer ("rotations", "cameras", "middlebury",
            "mat", "strecha", "colmap", "pycolmap", ...).
        label: the reference's name in metrics and reports ("truth",
            "pycolmap", ...).
        unregistered: ``{image name: why}`` for the images a reconstruction
            was given but left without a camera.
        info: what the producer reports about itself (pycolmap: its summary).
    """

    names: list[str]
    cam_from_world: np.ndarray
    _: KW_ONLY
    centers: np.ndarray | None = None
    K: np.ndarray | None = None
    source: str = ""
    label: str = ""
    unregistered: dict[str, str] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [str(n) for n in self.names]
        n = len(names)
        R = np.asarray(self.cam_from_world, dtype=np.float64)
        if R.shape != (n, 3, 3) and not (n == 0 and R.size == 0):
            raise ValueError(f"cam_from_world.shape={R.shape} but expected ({n}, 3, 3), one per name")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "cam_from_world", R.reshape(n, 3, 3))
        if self.centers is not None:
            C = np.asarray(self.centers, dtype=np.float64)
            if C.shape != (n, 3):
                raise ValueError(f"centers.shape={C.shape} but expected ({n}, 3)")
            object.__setattr__(self, "centers", C)
        if self.K is not None:
            K = np.asarray(self.K, dtype=np.float64)
            if K.shape not in ((n, 3, 3), (3, 3)):
                raise ValueError(f"K.shape={K.shape} but expected ({n}, 3, 3) or (3, 3)")
            object.__setattr__(self, "K", K)

    @property
    def R(self) -> np.ndarray:
        """(N, 3, 3) cam_from_world rotations (the same array as :attr:`cam_from_world`)."""
        return self.cam_from_world

    def replace(self, **changes: Any) -> "Reference":
        """A copy with ``changes`` applied (e.g. ``label="truth"``)."""
        return dataclasses.replace(self, **changes)
