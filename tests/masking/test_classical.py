"""Classical camera backend: proposals and GrabCut prompts on synthetic gripper scenes."""

import cv2
import numpy as np
import pytest

from mvtop_cli.errors import ConfigError
from mvtop_cli.masking.classical import ClassicalCameraBackend, ClassicalOptions
from mvtop_cli.masking.selection import select_masks

H, W = 480, 640
ORANGE, GREY_PART, GREY_FINGER = (210, 120, 40), (140, 140, 145), (125, 125, 125)


def make_scene(seed, part_rgb=ORANGE, finger_rgb=(128, 128, 128), split=False, noise=3.0):
    """A 640x480 RGB view of an L-shaped part (about 120 x 80 px, shaded, with a specular
    highlight) on a textured board with clutter, under a grey finger that covers one corner
    (or, with ``split``, crosses the whole part). Returns (image, visible part mask, ROI box
    (x0, y0, x1, y1) with a 30 px margin around the whole part)."""
    rng = np.random.default_rng(seed)
    low = cv2.resize(rng.normal(0, 1, (H // 32, W // 32, 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    grain = np.sin(xx * 0.35 + 3 * np.sin(yy * 0.02))[..., None]
    img = np.array([95, 105, 115], np.float32) + 14 * low + 8 * grain
    cv2.rectangle(img, (0, 400), (W, H), (60, 55, 50), -1)  # table edge
    cv2.circle(img, (470, 330), 30, (30, 30, 35), -1)  # receptacle hole
    cv2.line(img, (80, 60), (250, 440), (40, 70, 160), 9)  # cable

    cx, cy, angle = 330 + rng.uniform(-15, 15), 230 + rng.uniform(-15, 15), np.radians(rng.uniform(-25, 25))
    outline = np.array([[-60, -40], [60, -40], [60, 10], [20, 10], [20, 40], [-60, 40]], np.float32)
    c, s = np.cos(angle), np.sin(angle)
    pts = (outline @ np.array([[c, s], [-s, c]], np.float32) + [cx, cy]).astype(np.int32)
    part = np.zeros((H, W), np.uint8)
    cv2.fillPoly(part, [pts], 1)
    shade = 1.0 + 0.12 * (xx - cx) / 60.0 - 0.05 * (yy - cy) / 40.0
    img = np.where(part[..., None] > 0, np.array(part_rgb, np.float32) * shade[..., None], img)
    glint = np.zeros((H, W), np.float32)
    cv2.ellipse(glint, (int(cx - 20), int(cy - 15)), (16, 7), np.degrees(angle), 0, 360, 1.0, -1)
    glint = 0.8 * cv2.GaussianBlur(glint, (0, 0), 3)[..., None] * part[..., None]
    img = img * (1 - glint) + glint * np.array([250, 245, 235], np.float32)

    finger = np.zeros((H, W), np.uint8)
    fx, tip = int(cx + (0 if split else 45)), int(cy + (80 if split else 5))
    cv2.rectangle(finger, (fx - 17, 0), (fx + 17, tip), 1, -1)
    cv2.circle(finger, (fx, tip), 17, 1, -1)
    finger_shade = (1.0 + 0.08 * (xx - fx) / 17.0)[..., None]
    img = np.where(finger[..., None] > 0, np.array(finger_rgb, np.float32) * finger_shade, img)

    img = cv2.GaussianBlur(img, (0, 0), 0.7) + rng.normal(0, noise, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    ys, xs = np.nonzero(part)
    roi = (int(xs.min()) - 30, int(ys.min()) - 30, int(xs.max()) + 31, int(ys.max()) + 31)
    return image, (part > 0) & (finger == 0), roi


def iou(a, b):
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


def best_iou(masks, truth):
    return max((iou(m, truth) for m in masks), default=0.0)


@pytest.fixture(scope="module")
def backend():
    return ClassicalCameraBackend()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_best_proposal_matches_part_under_finger(backend, seed):
    image, truth, roi = make_scene(seed)
    masks = backend.proposals(image, roi)
    assert 1 <= len(masks) <= backend.options.max_proposals
    assert best_iou(masks, truth) >= 0.9
    x0, y0, x1, y1 = roi
    inside = np.zeros((H, W), bool)
    inside[y0:y1, x0:x1] = True
    for m in masks:
        assert m.shape == (H, W) and m.dtype == bool
        assert not (m & ~inside).any(), "proposals stay in the region of interest"
        assert m.sum() >= backend.options.min_area_px * 0.8  # bilinear upsampling may shave a little
    pairwise = [iou(a, b) for i, a in enumerate(masks) for b in masks[i + 1 :]]
    assert max(pairwise, default=0.0) <= backend.options.merge_iou + 0.02  # merged at work resolution


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_part_cut_in_two_by_finger_is_proposed_whole(backend, seed):
    image, truth, roi = make_scene(seed, split=True)
    n_pieces, _ = cv2.connectedComponents(truth.astype(np.uint8))
    assert n_pieces - 1 == 2
    # The two visible pieces as one proposal; the highlight touching the finger and a
    # sliver under it are lost (measured 0.87-0.97 over 12 seeds).
    assert best_iou(backend.proposals(image, roi), truth) >= 0.85


@pytest.mark.parametrize("seed,split", [(0, False), (1, False), (2, True), (3, True)])
def test_grey_part_under_grey_finger(backend, seed, split):
    # 15 grey levels between part and finger (and a background that comes close to the
    # part in places): measured 0.70-0.98 over 12 seeds, 0.73/0.70 at seed 0, where the
    # part leaks into look-alike background texture.
    image, truth, roi = make_scene(seed, part_rgb=GREY_PART, finger_rgb=GREY_FINGER, split=split)
    assert best_iou(backend.proposals(image, roi), truth) >= 0.7


def make_two_faced_part(seed, shade=0.55):
    """A 640x480 view of a box seen at an angle: its lit front face and its side face, the same
    off-white material at ``shade`` of the brightness, on the textured board of ``make_scene``.
    Returns (image, part mask, ROI box with a 30 px margin)."""
    rng = np.random.default_rng(seed)
    low = cv2.resize(rng.normal(0, 1, (H // 32, W // 32, 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    img = np.array([95, 105, 115], np.float32) + 14 * low
    cx, cy = 320 + rng.uniform(-15, 15), 230 + rng.uniform(-15, 15)
    w, h, depth, rise = 70 + rng.uniform(-10, 10), 90 + rng.uniform(-10, 10), 35.0, 18.0
    front = np.array([[cx, cy], [cx + w, cy], [cx + w, cy + h], [cx, cy + h]], np.float32)
    side = np.array([[cx - depth, cy - rise], [cx, cy], [cx, cy + h], [cx - depth, cy + h - rise]], np.float32)
    faces = []
    for poly, level in ((front, 1.0), (side, shade)):
        m = np.zeros((H, W), np.uint8)
        cv2.fillPoly(m, [np.rint(poly).astype(np.int32)], 1)
        img = np.where(m[..., None] > 0, np.array([235, 230, 215], np.float32) * level, img)
        faces.append(m > 0)
    img = cv2.GaussianBlur(img, (0, 0), 0.7) + rng.normal(0, 3.0, img.shape)
    part = faces[0] | faces[1]
    ys, xs = np.nonzero(part)
    roi = (int(xs.min()) - 30, int(ys.min()) - 30, int(xs.max()) + 31, int(ys.max()) + 31)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), part, roi


def test_differently_lit_faces_are_proposed_as_one_part(backend):
    """Colour, watershed and edges split a part into its faces; with ``adjacent_contact_px`` the
    union of touching regions proposes the whole part. Measured over seeds 0-5: best IoU
    0.72-0.995 (median 0.89), and 0.60-0.69 without the unions, where the best proposal is a face."""
    best, faces = [], []
    unions = ClassicalCameraBackend(adjacent_contact_px=3)
    for seed in range(6):
        image, truth, roi = make_two_faced_part(seed)
        best.append(best_iou(unions.proposals(image, roi), truth))
        faces.append(best_iou(backend.proposals(image, roi), truth))
    assert min(best) >= 0.7 and np.median(best) >= 0.88, best
    assert max(faces) < 0.7, faces


def test_whole_image_without_roi(backend):
    image, truth, _ = make_scene(4)
    masks = backend.proposals(image)
    assert len(masks) <= backend.options.max_proposals
    assert best_iou(masks, truth) >= 0.85  # the 640x480 view is worked on at 128x96


def test_roi_forms_agree(backend):
    image, _, (x0, y0, x1, y1) = make_scene(5)

    class Box:  # the shape of render.roi.Roi
        def __init__(self):
            self.x0, self.y0, self.width, self.height = x0, y0, x1 - x0, y1 - y0

    a = backend.proposals(image, (x0, y0, x1, y1))
    b = backend.proposals(image, Box())
    assert len(a) == len(b) and all(np.array_equal(p, q) for p, q in zip(a, b))
    with pytest.raises(ValueError, match="roi_box"):
        backend.proposals(image, (700, 10, 720, 30))


def test_proposals_are_deterministic(backend):
    image, _, roi = make_scene(6)
    first = backend.proposals(image, roi)
    again = ClassicalCameraBackend().proposals(image, roi)
    assert len(first) == len(again)
    assert all(np.array_equal(p, q) for p, q in zip(first, again))


def prompt_from(truth, shift, grow_px=2):
    shifted = np.roll(truth, shift, axis=(0, 1))
    kernel = np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)
    return cv2.dilate(shifted.astype(np.uint8), kernel).astype(bool)


@pytest.mark.parametrize("seed,shift", [(0, (0, 3)), (1, (3, 0)), (2, (-3, 0)), (3, (0, -3))])
def test_prompt_refines_offset_silhouette(backend, seed, shift):
    image, truth, _ = make_scene(seed)
    prompt = prompt_from(truth, shift)
    refined = backend.prompt(image, prompt)
    assert refined.shape == (H, W) and refined.dtype == bool
    assert iou(refined, truth) >= 0.9
    assert iou(refined, truth) > iou(prompt, truth) + 0.05


def test_prompt_on_grey_part_split_by_grey_finger(backend):
    image, truth, _ = make_scene(7, part_rgb=GREY_PART, finger_rgb=GREY_FINGER, split=True)
    prompt = prompt_from(truth, (2, -2))
    refined = backend.prompt(image, prompt)
    assert iou(refined, truth) >= 0.9 and iou(refined, truth) > iou(prompt, truth)


def red_disk_view(radius_px):
    rng = np.random.default_rng(0)
    image = np.full((H, W, 3), 110, np.float32)
    cv2.circle(image, (320, 250), radius_px, (200, 30, 30), -1)
    return np.clip(image + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)


def test_prompt_grows_into_ring_but_falls_back_when_it_takes_most_of_it(backend):
    # The prompt is a 25 px disk; the probable-background ring reaches 12 px further.
    prompt = np.zeros((H, W), np.uint8)
    cv2.circle(prompt, (320, 250), 25, 1, -1)
    prompt = prompt.astype(bool)
    truth = np.zeros((H, W), np.uint8)
    cv2.circle(truth, (320, 250), 30, 1, -1)
    grown = backend.prompt(red_disk_view(30), prompt)
    assert iou(grown, truth.astype(bool)) >= 0.97
    # A 36 px part would take ~90% of the ring: beyond what a converged estimate allows,
    # so the rule returns the prompt; without the rule GrabCut does take it.
    assert np.array_equal(backend.prompt(red_disk_view(36), prompt), prompt)
    lax = ClassicalCameraBackend(prompt_max_ring_fraction=1.0)
    assert lax.prompt(red_disk_view(36), prompt).sum() > 1.8 * prompt.sum()


def test_prompt_edge_cases(backend):
    image, truth, _ = make_scene(8)
    assert not backend.prompt(image, np.zeros((H, W), bool)).any()
    prompt = prompt_from(truth, (2, 2))
    assert np.array_equal(backend.prompt(image, prompt), ClassicalCameraBackend().prompt(image, prompt))
    with pytest.raises(ValueError, match="does not match"):
        backend.prompt(image, prompt[:-1])
    with pytest.raises(ValueError, match="RGB uint8"):
        backend.proposals(image.astype(np.float32))


def test_selected_proposal_identifies_the_true_placement(backend):
    # Algorithm 1 end to end on one camera: candidate placements are the visible part
    # shifted in 6 px steps; the unshifted one must win and its proposal fit the part.
    image, truth, (x0, y0, x1, y1) = make_scene(9)
    proposals = [m[y0:y1, x0:x1] for m in backend.proposals(image, (x0, y0, x1, y1))]
    shifts = [(dy, dx) for dy in (-12, -6, 0, 6, 12) for dx in (-12, -6, 0, 6, 12)]
    rendered = np.stack([np.roll(truth, s, axis=(0, 1))[y0:y1, x0:x1] for s in shifts])
    sel = select_masks({"cam": proposals}, {"cam": rendered}, {"cam": 1.0})
    assert shifts[sel.best_pose_index] == (0, 0)
    assert iou(sel.masks["cam"], truth[y0:y1, x0:x1]) >= 0.9


def test_options_are_validated():
    with pytest.raises(ConfigError, match="did you mean 'seed'"):
        ClassicalCameraBackend(sead=1)
    with pytest.raises(ConfigError, match="merge_iou"):
        ClassicalCameraBackend(merge_iou=1.5)
    with pytest.raises(ConfigError, match="'max_proposals'"):
        ClassicalCameraBackend(max_proposals="many")
    b = ClassicalCameraBackend(ClassicalOptions(seed=3), cluster_counts=[3, 5], max_proposals=4)
    assert (b.options.seed, b.options.cluster_counts, b.options.max_proposals) == (3, (3, 5), 4)
    image, _, roi = make_scene(10)
    assert len(b.proposals(image, roi)) <= 4
