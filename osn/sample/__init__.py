"""Sampling (``osn sample``): valid scale configurations from a trained scale network, no ground truth.

Modules:

* :mod:`~osn.sample.configurations`: :func:`sample_configurations` (rejection sampling of the
  normalised scale box) and :class:`Samples` (``RUN/samples.npz``).
"""

from osn.sample.configurations import Samples, sample_configurations

__all__ = ["Samples", "sample_configurations"]
