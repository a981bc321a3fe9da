"""Rotation averaging: robust IRLS (paper 1), Weiszfeld, and SDP-cSO(3) (paper 2)."""

from pipeline.averaging.result import AveragingResult

__all__ = ["AveragingResult"]
