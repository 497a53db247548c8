"""Mask selection (Algorithms 1-2): batched scoring against a plain loop, and the right pose."""

import cv2
import numpy as np
import pytest

from mvtop_cli.masking.selection import select_masks


def loop_iou(a, b, empty_score=1.0):
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else empty_score


def loop_select(proposals, rendered, weights):
    """Algorithms 1 and 2 written as in the paper: per pose, per sensor, the proposal with
    the best IoU (``>=``: the last of equals); the first pose with the highest weighted sum.
    Returns (best pose, score, masks, per-pose scores)."""
    n_poses = len(next(iter(rendered.values())))
    best_pose, best_score, best_masks = 0, 0.0, {s: None for s in rendered}
    scores = []
    for n in range(n_poses):
        s_n, masks_n = 0.0, {}
        for sensor, rend in rendered.items():
            s_star, m_star = 0.0, None
            for m in proposals.get(sensor, []):
                s_i = loop_iou(rend[n], m)
                if s_i >= s_star:
                    s_star, m_star = s_i, m
            s_n += weights[sensor] * s_star
            masks_n[sensor] = m_star if s_star > 0 else None
        scores.append(s_n)
        if s_n > best_score:
            best_pose, best_score, best_masks = n, s_n, masks_n
    return best_pose, best_score, best_masks, np.array(scores)


def blob(shape, centre, axes, angle=0.0):
    m = np.zeros(shape, np.uint8)
    cv2.ellipse(m, (int(centre[0]), int(centre[1])), (int(axes[0]), int(axes[1])), angle, 0, 360, 1, -1)
    return m.astype(bool)


def random_masks(rng, n, shape=(60, 80)):
    return np.stack([
        blob(shape, rng.uniform(10, 70, 2), rng.uniform(4, 25, 2), rng.uniform(0, 180)) for _ in range(n)
    ])


@pytest.mark.parametrize("seed", range(5))
def test_select_masks_matches_loop(seed):
    rng = np.random.default_rng(seed)
    n_poses = 40
    rendered = {s: random_masks(rng, n_poses) for s in ("cam_left", "cam_right", "tactile_left", "tactile_right")}
    proposals = {
        "cam_left": list(random_masks(rng, 30)),
        "cam_right": list(random_masks(rng, 12)),
        "tactile_left": list(random_masks(rng, 3)),
        # tactile_right has no proposals: contributes 0, gets None
    }
    proposals["cam_right"].append(proposals["cam_right"][0].copy())  # a tie: the later copy wins
    weights = {"cam_left": 0.25, "cam_right": 0.25, "tactile_left": 0.3, "tactile_right": 0.2}
    sel = select_masks(proposals, rendered, weights)
    pose, score, masks, scores = loop_select(proposals, rendered, weights)
    np.testing.assert_allclose(sel.per_pose_scores, scores, rtol=0, atol=1e-12)
    assert sel.best_pose_index == pose
    assert sel.score == pytest.approx(score, abs=1e-12)
    assert sel.masks.keys() == masks.keys()
    for sensor, m in masks.items():
        if m is None:
            assert sel.masks[sensor] is None
        else:
            assert np.array_equal(sel.masks[sensor], m)
    assert sel.masks["tactile_right"] is None
    assert np.all(sel.per_sensor_choice["tactile_right"] == -1)
    choice = sel.per_sensor_choice["cam_right"]
    copy = len(proposals["cam_right"]) - 1
    assert np.any(choice == copy) and not np.any(choice == 0), "of equal proposals the later one is kept"


def test_picks_the_pose_that_explains_both_sensors():
    shape = (96, 96)
    rng = np.random.default_rng(1)
    # Candidate poses move the object's camera blob and tactile contact patch together.
    offsets = [(dx, dy) for dx in (-16, -8, 0, 8, 16) for dy in (-16, -8, 0, 8, 16)]
    truth_index = offsets.index((8, -8))

    def cam(o):
        return blob(shape, (48 + o[0], 48 + o[1]), (22, 12), 30)

    def tac(o):
        return blob(shape, (40 + o[0] / 2, 50 - o[1] / 2), (9, 14), 0)

    rendered = {"cam": np.stack([cam(o) for o in offsets]), "tac": np.stack([tac(o) for o in offsets])}
    true_cam, true_tac = cam(offsets[truth_index]), tac(offsets[truth_index])
    # Observed proposals: the truth, eroded a little (imperfect segmentation), among
    # distractors (a finger, a part of the object, the background).
    observed_cam = cv2.erode(true_cam.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    cam_props = [blob(shape, (10, 10), (30, 8)), observed_cam, true_cam & (np.arange(96)[None] < 50), ~true_cam]
    observed_tac = true_tac & (rng.random(shape) > 0.05)
    tac_props = [observed_tac, blob(shape, (80, 80), (6, 6))]
    sel = select_masks({"cam": cam_props, "tac": tac_props}, rendered, {"cam": 0.5, "tac": 0.5})
    assert sel.best_pose_index == truth_index
    assert np.array_equal(sel.masks["cam"], observed_cam)
    assert np.array_equal(sel.masks["tac"], observed_tac)
    assert sel.score == pytest.approx(
        0.5 * loop_iou(true_cam, observed_cam) + 0.5 * loop_iou(true_tac, observed_tac)
    )
    assert sel.per_sensor_iou["cam"][truth_index] == pytest.approx(loop_iou(true_cam, observed_cam))


def test_weights_decide_between_disagreeing_sensors():
    shape = (40, 40)
    a, b = blob(shape, (12, 20), (6, 6)), blob(shape, (28, 20), (6, 6))
    rendered = {"s1": np.stack([a, b]), "s2": np.stack([a, b])}
    proposals = {"s1": [a], "s2": [b]}  # s1 sees pose 0, s2 sees pose 1
    assert select_masks(proposals, rendered, {"s1": 0.7, "s2": 0.3}).best_pose_index == 0
    assert select_masks(proposals, rendered, {"s1": 0.3, "s2": 0.7}).best_pose_index == 1
    tie = select_masks(proposals, rendered, {"s1": 0.5, "s2": 0.5})
    assert tie.best_pose_index == 0, "Algorithm 1 replaces the best pose only on a strictly higher score"
    # At pose 0, s2's only proposal does not overlap the render: no observation for s2.
    assert tie.masks["s2"] is None and np.array_equal(tie.masks["s1"], a)


def test_no_overlap_anywhere_selects_nothing():
    shape = (30, 30)
    rendered = {"cam": np.stack([blob(shape, (8, 8), (4, 4)), blob(shape, (8, 22), (4, 4))])}
    sel = select_masks({"cam": [blob(shape, (22, 22), (4, 4))]}, rendered, {"cam": 1.0})
    assert sel.score == 0.0 and sel.masks == {"cam": None}
    np.testing.assert_array_equal(sel.per_pose_scores, [0.0, 0.0])


def test_proposals_as_array_and_as_list_agree():
    rng = np.random.default_rng(3)
    rendered = {"cam": random_masks(rng, 20)}
    props = random_masks(rng, 6)
    a = select_masks({"cam": props}, rendered, {"cam": 1.0})
    b = select_masks({"cam": list(props)}, rendered, {"cam": 1.0})
    np.testing.assert_array_equal(a.per_pose_scores, b.per_pose_scores)
    assert a.best_pose_index == b.best_pose_index


def test_input_errors():
    rng = np.random.default_rng(4)
    r = random_masks(rng, 3)
    with pytest.raises(ValueError, match="no weight"):
        select_masks({"cam": list(r)}, {"cam": r}, {})
    with pytest.raises(ValueError, match="no rendered masks"):
        select_masks({"cam": list(r), "tac": list(r)}, {"cam": r}, {"cam": 1.0})
    with pytest.raises(ValueError, match="one P"):
        select_masks({}, {"cam": r, "tac": r[:2]}, {"cam": 0.5, "tac": 0.5})
    with pytest.raises(ValueError, match=">= 0"):
        select_masks({}, {"cam": r}, {"cam": -1.0})
    with pytest.raises(ValueError, match="must be"):
        select_masks({"cam": [r[0][:-1]]}, {"cam": r}, {"cam": 1.0})
    with pytest.raises(ValueError, match="P = 0"):
        select_masks({}, {"cam": r[:0]}, {"cam": 1.0})
