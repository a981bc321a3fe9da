"""References to evaluate against: true cameras (:mod:`.truth`) and reconstructions made here (:mod:`.incremental`).

Every reference is one :class:`Reference`. ``python -m pipeline.reference`` runs the
pycolmap incremental reconstruction (:func:`pipeline.reference.incremental.main_cli`).
"""

from pipeline.reference.incremental import (IncrementalReferenceStage, ReferenceConfig, known_intrinsics, main,
                                            main_cli)
from pipeline.reference.models import load_reference
from pipeline.reference.truth import read_reference
from pipeline.reference.types import Reference

__all__ = ["Reference", "read_reference", "ReferenceConfig", "IncrementalReferenceStage", "known_intrinsics",
           "load_reference", "main", "main_cli"]
