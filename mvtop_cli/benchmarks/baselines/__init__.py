"""Baselines that are not M-VTOP, fed with the same observations: ``points`` turns observations
into labelled point sets (pure numpy), ``observations`` does so for a whole log, ``chsel_runner``
registers them with CHSEL (optional dependencies, imported when used) and ``run`` writes the
result as an estimate folder for ``mvtop eval`` and ``mvtop benchmark accuracy``.

``points`` and ``chsel_runner`` sit beside the core (geometry only); ``observations`` and
``run`` wire io and the masking to them, at the level of ``pipelines``.
"""
