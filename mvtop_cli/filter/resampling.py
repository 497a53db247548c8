"""Importance resampling schemes, registered by name with one signature (Algorithm 3, line 9).

Every scheme is ``scheme(log_weights (N,), n_out, rng) -> indices (n_out,) int`` and is
unbiased: the expected number of copies of particle ``i`` is ``n_out * w_i``. Particles of
zero weight (log-weight ``-inf``) are never drawn. References: Douc, Cappé & Moulines,
"Comparison of resampling schemes for particle filtering" (2005); Kitagawa (1996) for
systematic/stratified; Liu & Chen (1998) for residual resampling.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable

import numpy as np

from .particles import ParticleSet, normalise_log_weights

ResamplingScheme = Callable[[np.ndarray, int, np.random.Generator], np.ndarray]

_SCHEMES: dict[str, ResamplingScheme] = {}


def register(name: str) -> Callable[[ResamplingScheme], ResamplingScheme]:
    """Decorator adding a scheme to the registry under ``name``."""

    def add(scheme: ResamplingScheme) -> ResamplingScheme:
        if name in _SCHEMES:
            raise ValueError(f"resampling scheme {name!r} is already registered")
        _SCHEMES[name] = scheme
        return scheme

    return add


def available_schemes() -> tuple[str, ...]:
    """Registered scheme names, sorted (for config validation)."""
    return tuple(sorted(_SCHEMES))


def get_scheme(name: str) -> ResamplingScheme:
    """The scheme registered as ``name``; ``ValueError`` with a suggestion otherwise."""
    try:
        return _SCHEMES[name]
    except KeyError:
        close = difflib.get_close_matches(str(name), _SCHEMES, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown resampling scheme {name!r}{hint}; expected one of {', '.join(available_schemes())}"
        ) from None


def _weights(log_weights: np.ndarray) -> np.ndarray:
    return np.exp(normalise_log_weights(log_weights))


def _invert_cdf(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Indices ``i`` with ``cdf[i-1] <= u < cdf[i]`` for sorted or unsorted ``u`` in [0, 1)."""
    cdf = np.cumsum(w)
    idx = np.searchsorted(cdf, u * cdf[-1], side="right")
    # Rounding can push u * cdf[-1] onto cdf[-1]; never hand out a trailing zero-weight particle.
    last_positive = int(np.flatnonzero(w > 0)[-1])
    return np.minimum(idx, last_positive)


@register("multinomial")
def multinomial(log_weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """Independent draws from the categorical distribution of the weights (highest variance)."""
    return _invert_cdf(_weights(log_weights), rng.random(n_out))


@register("stratified")
def stratified(log_weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """One independent uniform draw in each of ``n_out`` equal strata of [0, 1)."""
    u = (np.arange(n_out) + rng.random(n_out)) / n_out
    return _invert_cdf(_weights(log_weights), u)


@register("systematic")
def systematic(log_weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """One uniform offset shared by ``n_out`` evenly spaced points: particle ``i`` gets
    ``floor(n_out w_i)`` or ``ceil(n_out w_i)`` copies. Lowest variance in practice."""
    u = (np.arange(n_out) + rng.random()) / n_out
    return _invert_cdf(_weights(log_weights), u)


@register("residual")
def residual(log_weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """``floor(n_out w_i)`` deterministic copies, the remainder drawn multinomially from
    the residual weights ``n_out w_i - floor(n_out w_i)``."""
    w = _weights(log_weights)
    expected = n_out * w
    counts = np.floor(expected).astype(np.int64)
    rest = n_out - int(counts.sum())
    idx = np.repeat(np.arange(len(w)), counts)
    if rest > 0:
        res = np.clip(expected - counts, 0.0, None)
        if res.sum() <= 0:  # only through rounding; fall back to the weights themselves
            res = w
        idx = np.concatenate([idx, _invert_cdf(res / res.sum(), rng.random(rest))])
    return np.sort(idx)


def resample(
    particles: ParticleSet, scheme: str, rng: np.random.Generator, n_out: int | None = None
) -> ParticleSet:
    """Resample ``particles`` with the named scheme into ``n_out`` (default N) equally
    weighted particles."""
    n_out = len(particles) if n_out is None else int(n_out)
    idx = get_scheme(scheme)(particles.log_weights, n_out, rng)
    return ParticleSet.uniform(particles.poses[idx])


def resample_if_needed(
    particles: ParticleSet, ess_threshold_fraction: float, scheme: str, rng: np.random.Generator
) -> tuple[ParticleSet, bool]:
    """Resample when ``ESS < ess_threshold_fraction * N`` (adaptive resampling).

    ``ess_threshold_fraction`` in [0, 1]: 0 never resamples, 1 resamples whenever the
    weights are not exactly uniform. Returns ``(particles, resampled)``; the rng is only
    used when resampling happens.
    """
    if not 0.0 <= ess_threshold_fraction <= 1.0:
        raise ValueError(f"ess_threshold_fraction must be in [0, 1], got {ess_threshold_fraction!r}")
    get_scheme(scheme)  # fail on a bad name even when no resampling is needed
    if particles.ess() < ess_threshold_fraction * len(particles):
        return resample(particles, scheme, rng), True
    return particles, False
