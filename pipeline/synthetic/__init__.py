"""Synthetic data with known truth.

- :mod:`pipeline.synthetic.graphs`: view graphs drawn from the protocols of
  paper 1 (Fig. 4), paper 2 (§5.1) and a k-nearest-neighbour scale protocol.
- :mod:`pipeline.synthetic.render`: rendered image scenes with known cameras.

All generators are seeded and deterministic: the same arguments give the same
arrays on every run.
"""
