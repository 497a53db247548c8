"""Visuo-tactile matching score (eq. 1-2): IoU arrays in, per-particle log-likelihood out.

Rendering and IoU computation live elsewhere; this module only turns an IoU table into
``log s^(n)``, the log of eq. 1's softmax over particles, which eq. 7 uses as the
visuo-tactile log-likelihood. The contact term (eq. 8-9) comes from
``mvtop_cli.contact.likelihood`` and is simply added in log space (eq. 6).

Missing sensors. A sensor whose IoU column is NaN for every particle is absent from
this frame (no image, or no usable observed mask). Its importance weight is dropped and
the weights of the sensors present are rescaled to sum to one, as eq. 2 requires
(``sum gamma + sum nu = 1``), so the score keeps the range [0, 1] and the temperature
keeps its meaning whatever the number of sensors. Default weights follow the paper
(``gamma_i = 1/N_T``, ``nu_j = 1/N_V``: modalities weighted equally), with ``N_T`` and
``N_V`` counting the sensors present in the frame; given weights keep their ratios. A
frame without any sensor carries no information: every particle gets ``-log N``.

With ``renormalise=False`` the given weights are used as they are, absent sensors simply
dropped: each sensor then contributes the same ``gamma_i IoU_i / tau`` to the
log-likelihood whichever other sensors are present, as independent sensors' log-likelihoods
add. The estimator scores this way, so a frame that holds only tactile images (sensors at
different rates) counts as the tactile part of a full frame rather than as a whole frame
of evidence about what touch alone cannot see.

A NaN for only some particles in a column (IoU undefined for those renders) scores that
term as 0, the worst possible IoU, so such particles are never favoured.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp


def _iou_table(iou: np.ndarray | None, n: int | None, name: str) -> np.ndarray | None:
    if iou is None:
        return None
    a = np.asarray(iou, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{name} must have shape (N, n_sensors), got {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} rows, expected {n} (one per particle)")
    if np.isinf(a).any():
        raise ValueError(f"{name} contains infinite IoU values")
    return a


def _importance(given: np.ndarray | None, present: np.ndarray, name: str) -> np.ndarray:
    """Per-sensor weights (n_sensors,) before the joint renormalisation; 0 for absent sensors."""
    k = len(present)
    if given is None:
        n_present = int(present.sum())
        return np.where(present, 1.0 / max(n_present, 1), 0.0)
    g = np.asarray(given, dtype=np.float64)
    if g.shape != (k,):
        raise ValueError(f"{name} must have shape ({k},), got {g.shape}")
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise ValueError(f"{name} must be finite and >= 0, got {g}")
    return np.where(present, g, 0.0)


def sensor_weights(
    present_tactile: np.ndarray,
    present_vision: np.ndarray,
    gamma: np.ndarray | None = None,
    nu: np.ndarray | None = None,
    renormalise: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Importance weights ``(gamma (N_T,), nu (N_V,))`` actually used in eq. 2 for one frame.

    present_tactile, present_vision : (N_T,) / (N_V,) bool
      Which sensors have an observation in this frame.
    Absent sensors get 0; the others keep the given ratios (defaults 1/N_T and 1/N_V over
    the present sensors) and, with ``renormalise``, are rescaled to sum to one together
    (without it, given weights are kept as they are). All zeros when no present sensor has
    a positive weight.
    """
    pt = np.asarray(present_tactile, dtype=bool)
    pv = np.asarray(present_vision, dtype=bool)
    g = _importance(gamma, pt, "gamma")
    v = _importance(nu, pv, "nu")
    if not renormalise:
        return g, v
    total = g.sum() + v.sum()
    if total <= 0:
        return np.zeros_like(g), np.zeros_like(v)
    return g / total, v / total


def visuo_tactile_score(
    iou_tactile: np.ndarray | None,
    iou_vision: np.ndarray | None,
    gamma: np.ndarray | None = None,
    nu: np.ndarray | None = None,
    renormalise: bool = True,
) -> np.ndarray:
    """The matching score ``s~_n`` of eq. 2 for every particle, (N,) in [0, 1]: the
    importance-weighted sum of the IoUs (arguments as for ``visuo_tactile_log_score``;
    ``renormalise`` as for ``sensor_weights``).

    Unlike eq. 1's softmax, ``s~ / tau`` does not depend on which other particles are
    scored with it, so it is the log-likelihood to use when poses scored in different
    calls are compared (Metropolis moves, searches keeping earlier candidates): eq. 1's
    normalisation over the batch would add a batch-dependent constant."""
    tac = _iou_table(iou_tactile, None, "iou_tactile")
    n = None if tac is None else tac.shape[0]
    vis = _iou_table(iou_vision, n, "iou_vision")
    if vis is not None:
        n = vis.shape[0]
    if n is None:
        raise ValueError("at least one of iou_tactile and iou_vision must be given")
    if tac is None:
        tac = np.zeros((n, 0))
    if vis is None:
        vis = np.zeros((n, 0))
    g, v = sensor_weights(
        ~np.all(np.isnan(tac), axis=0), ~np.all(np.isnan(vis), axis=0), gamma, nu, renormalise
    )
    # eq. 2; isolated NaNs (and absent sensors, whose weight is 0) contribute nothing.
    return np.nan_to_num(tac, nan=0.0) @ g + np.nan_to_num(vis, nan=0.0) @ v


def visuo_tactile_log_score(
    iou_tactile: np.ndarray | None,
    iou_vision: np.ndarray | None,
    gamma: np.ndarray | None,
    nu: np.ndarray | None,
    temperature: float,
) -> np.ndarray:
    """Log of the visuo-tactile score ``s^(n)`` of eq. 1 for every particle.

    iou_tactile : (N, N_T) float or None
      IoU between observed tactile mask ``i`` and the mask rendered for particle ``n``;
      a column of NaN marks a sensor missing in this frame. None means no tactile sensor.
    iou_vision : (N, N_V) float or None
      The same for the cameras.
    gamma, nu : (N_T,) / (N_V,) float or None
      Sensor importance weights (>= 0); None for the paper's defaults. See the module
      docstring for how they are renormalised over the sensors present.
    temperature : float
      ``tau`` of eq. 1 (> 0): an IoU-score difference of ``tau`` is a factor ``e`` in
      likelihood.
    Returns (N,) float: ``s~_n / tau - logsumexp_m(s~_m / tau)``, computed in log space so
    that tiny temperatures (1e-4) neither overflow nor underflow. ``exp`` of the result
    sums to one over particles.
    """
    if not np.isfinite(temperature) or temperature <= 0:
        raise ValueError(f"temperature must be finite and > 0, got {temperature!r}")
    score = visuo_tactile_score(iou_tactile, iou_vision, gamma, nu)
    if len(score) == 0:
        raise ValueError("IoU tables have no particles (N = 0)")
    # Shift by the best score before dividing: the log-softmax is unchanged, and the
    # logits stay small near the top, where precision matters, even for tiny tau.
    logits = (score - score.max()) / temperature
    return logits - logsumexp(logits)
