"""Evaluation: metrics (:mod:`.metrics`), comparisons against references (:mod:`.compare`), analysis
(:mod:`.analysis`) and the report (:mod:`.report`, :mod:`.plots`). ``python -m pipeline.evaluate`` is
:func:`pipeline.evaluation.compare.main_cli`.
"""
