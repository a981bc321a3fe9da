"""Moved: the truth readers are :mod:`pipeline.reference.truth`, the type :class:`pipeline.reference.Reference`.

This alias keeps old imports working until every caller has moved.
"""

from pipeline.reference.truth import *  # noqa: F401,F403
from pipeline.reference.types import Reference  # noqa: F401
