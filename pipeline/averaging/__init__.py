"""Rotation averaging: robust IRLS (paper 1), Weiszfeld, and SDP-cSO(3) (paper 2)."""

from .result import AveragingResult

__all__ = ["AveragingResult"]
