"""References to evaluate against: true cameras (:mod:`.truth`) and reconstructions made here.

The reconstructions are pycolmap peers (:mod:`.peer`): incremental (:mod:`.incremental`) and
global, GLOMAP (:mod:`.global_mapping`). Every reference is one :class:`Reference`.
``python -m pipeline.reference`` runs the pycolmap incremental reconstruction
(:func:`pipeline.reference.incremental.main_cli`); ``python -m pipeline.reference.global_mapping``
the global one (imported from its module, so that ``-m`` runs it cleanly).
"""

from pipeline.reference.incremental import (IncrementalReferenceStage, ReferenceConfig, known_intrinsics, main,
                                            main_cli)
from pipeline.reference.models import load_reference
from pipeline.reference.truth import read_reference
from pipeline.reference.types import Reference

__all__ = ["Reference", "read_reference", "ReferenceConfig", "IncrementalReferenceStage", "known_intrinsics",
           "load_reference", "main", "main_cli"]
