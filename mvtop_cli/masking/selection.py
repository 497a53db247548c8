"""Zero-shot mask selection: score proposals against rendered pose candidates (paper Algorithms 1-2).

For every candidate pose ``n`` and sensor ``s`` the proposal with the best IoU against the
pose's rendered mask is chosen (Algorithm 2); the pose score is the sensor-weighted sum of
those IoUs (the weighting of eq. 2). The pose with the highest score wins and its per-sensor
proposals become the observed masks (Algorithm 1). Everything works on arrays, so the
renderer that produced the reference masks does not matter here.

Tie rules follow the paper's pseudo-code: within a sensor, Algorithm 2 keeps a proposal when
``s_i >= s*``, so among equally good proposals the *last* one wins; across poses, Algorithm 1
replaces the best pose only when ``s_n > s*``, so the *first* of equally scored poses wins.
One deliberate deviation: Algorithm 2 starting from ``s* = 0`` with ``>=`` would "select" the
last proposal of a sensor even when no proposal overlaps the render at all; here such a
sensor gets ``None`` (no consistent observation), as does a sensor with no proposals.
If every pose scores 0, Algorithm 1 never assigns masks, so all masks are ``None``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mvtop_cli.bitmasks import iou_matrix


@dataclass(frozen=True)
class Selection:
    """Result of Algorithm 1 over P candidate poses.

    best_pose_index : int, index of the winning pose (the first of equal scores)
    score : float, its weighted score ``s*``
    masks : sensor -> (h, w) bool proposal selected at the winning pose, or None when the
        sensor had no proposals or none of them overlaps the rendered mask
    per_pose_scores : (P,) float64, weighted score of every pose
    per_sensor_iou : sensor -> (P,) float64, best proposal IoU of every pose
    per_sensor_choice : sensor -> (P,) int64, index of that proposal (-1 if no proposals)
    """

    best_pose_index: int
    score: float
    masks: dict[str, np.ndarray | None]
    per_pose_scores: np.ndarray
    per_sensor_iou: dict[str, np.ndarray]
    per_sensor_choice: dict[str, np.ndarray]


def select_masks(
    proposals: Mapping[str, Sequence[np.ndarray] | np.ndarray],
    rendered: Mapping[str, np.ndarray],
    weights: Mapping[str, float],
    empty_score: float = 1.0,
) -> Selection:
    """Pick the candidate pose whose renders best match the proposals, and its masks.

    proposals : sensor -> list of (h, w) bool masks (or an (M, h, w) array) from a
        zero-shot backend, cropped like that sensor's renders
    rendered : sensor -> (P, h, w) bool reference masks, one per candidate pose; every
        sensor has the same P
    weights : sensor -> importance weight (gamma_i / nu_j of eq. 2) for every rendered sensor
    empty_score : IoU of an empty proposal with an empty render (see ``bitmasks.iou_matrix``)

    Sensors in ``rendered`` without proposals contribute 0 and get ``None``.
    Raises ValueError on proposals for a sensor with no renders, a missing or negative
    weight, mismatched shapes or no candidate poses.
    """
    extra = sorted(set(proposals) - set(rendered))
    if extra:
        raise ValueError(f"proposals for sensors {extra} have no rendered masks")
    missing = sorted(set(rendered) - set(weights))
    if missing:
        raise ValueError(f"no weight for sensors {missing}")
    bad = {s: w for s, w in weights.items() if s in rendered and not (np.isfinite(w) and w >= 0)}
    if bad:
        raise ValueError(f"sensor weights must be finite and >= 0, got {bad}")
    if not rendered:
        raise ValueError("no rendered masks: need at least one sensor")
    counts = {s: np.shape(r)[0] if np.ndim(r) == 3 else None for s, r in rendered.items()}
    if None in counts.values() or len(set(counts.values())) != 1:
        raise ValueError(f"rendered masks must be (P, h, w) with one P for all sensors, got {counts}")
    n_poses = next(iter(counts.values()))
    if n_poses == 0:
        raise ValueError("no candidate poses (P = 0)")

    scores = np.zeros(n_poses, dtype=np.float64)
    per_sensor_iou: dict[str, np.ndarray] = {}
    per_sensor_choice: dict[str, np.ndarray] = {}
    stacks: dict[str, np.ndarray | None] = {}
    for sensor, rend in rendered.items():
        props = proposals.get(sensor)
        stack = None
        if props is not None and len(props) > 0:
            stack = np.asarray(props if isinstance(props, np.ndarray) else np.stack(list(props)), dtype=bool)
        stacks[sensor] = stack
        if stack is None:
            per_sensor_iou[sensor] = np.zeros(n_poses)
            per_sensor_choice[sensor] = np.full(n_poses, -1, dtype=np.int64)
            continue
        iou = iou_matrix(rend, stack, empty_score)  # (P, M)
        m = iou.shape[1]
        # Algorithm 2 keeps a proposal when s_i >= s*: the last maximum wins.
        last_best = m - 1 - np.argmax(iou[:, ::-1], axis=1)
        best = iou[np.arange(n_poses), last_best]
        per_sensor_iou[sensor] = best
        per_sensor_choice[sensor] = last_best.astype(np.int64)
        scores += float(weights[sensor]) * best

    best_pose = int(np.argmax(scores))  # Algorithm 1: strict '>', the first maximum wins
    score = float(scores[best_pose])
    masks: dict[str, np.ndarray | None] = {}
    for sensor, stack in stacks.items():
        chosen = None
        if stack is not None and score > 0 and per_sensor_iou[sensor][best_pose] > 0:
            chosen = stack[per_sensor_choice[sensor][best_pose]].copy()
        masks[sensor] = chosen
    return Selection(best_pose, score, masks, scores, per_sensor_iou, per_sensor_choice)
