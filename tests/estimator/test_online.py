"""The online API: an ``Estimator`` built from a config and fed one frame at a time gives the
track ``mvtop estimate`` writes for the same frames."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.estimator import Estimator, FrameEstimate
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate, log_topics, sensor_topics
from mvtop_cli.pipelines.track import TRACK_CSV_HEADER, track_csv_row
from mvtop_cli.records import Frame

ROOT = Path(__file__).resolve().parents[2]
FRAMES = 6


def test_online_steps_give_the_offline_track(tmp_path):
    log_path = ROOT / "sample_logs" / "conn2.mcap"
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=120))
    estimate(log_path, cfg, tmp_path / "offline", EstimateOptions(max_frames=FRAMES))
    offline = (tmp_path / "offline" / "track.csv").read_text().splitlines()

    rows = [TRACK_CSV_HEADER]
    with McapLog(log_path) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        # the fingers occlude the part: their TF frames come from the log's TF, as a robot's tf2 buffer would
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        for frame, _ in zip(reader, range(FRAMES)):
            assert isinstance(frame, Frame)
            result = estimator.step(frame)
            assert isinstance(result, FrameEstimate) and result.covariance.shape == (6, 6)
            assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
            rows.append(track_csv_row(result))
    assert rows == offline
    assert len(rows) == FRAMES + 1


def test_moving_occluders_need_a_frame_pose():
    """A config with a gripper-mounted mesh asks for ``frame_pose`` when it is first needed,
    naming the TF frame."""
    cfg = load_config(ROOT / "configs" / "cube.yaml")
    moving = [e.frame for e in cfg.environment if e.occlude and e.frame != cfg.frames.world]
    assert moving == ["finger_left", "finger_right"]
    estimator = Estimator.from_config(replace(cfg, modalities=("vision",)))
    with McapLog(ROOT / "sample_logs" / "cube.mcap") as log:
        frame = next(iter(FrameReader(log, sensor_topics(cfg), log_topics(cfg))))
    with pytest.raises(ValueError, match=f"TF frame {moving[0]!r}: give the Estimator a frame_pose"):
        estimator.step(frame)



def test_the_contact_signal_moves_the_particles_without_the_contact_modality():
    """Vision only (M-VOP): the frames still carry the log's contact signal, and the motion
    model follows it (Algorithm 3-4's c_k): a frame in contact spreads the belief's rotation by
    the contact sigma, one out of contact by the free one (the cube config: 0.25 and 0.1 deg per
    axis, a variance ratio of 6.25). With nothing observed the frame has no evidence at all: no
    contact likelihood without the contact modality."""
    cfg = load_config(ROOT / "configs" / "cube.yaml")
    cfg = replace(cfg, modalities=("vision",), filter=replace(cfg.filter, num_particles=400))
    f = cfg.filter
    expected = (f.sigma_high_rotation_deg / f.sigma_low_rotation_deg) ** 2
    added = {}
    with McapLog(ROOT / "sample_logs" / "cube.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        frames = [frame for frame, _ in zip(reader, range(30))]
        assert [fr.contact for fr in frames[:2]] == [False, False] and any(fr.contact for fr in frames)
        for contact in (False, True):
            estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
            estimator.step(frames[0])
            before = np.trace(estimator.particles.spread(estimator.fold).covariance[3:, 3:])
            estimator.step(replace(frames[1], cameras={}, contact=contact))
            added[contact] = np.trace(estimator.particles.spread(estimator.fold).covariance[3:, 3:]) - before
    assert added[False] > 0
    assert added[True] / added[False] == pytest.approx(expected, rel=0.3)

def _steps(name: str, modalities: tuple[str, ...], frames: int, suspect: float | None = 0.4,
           rival_every: int = 0, first_frame_rounds: int | None = None) -> list[FrameEstimate]:
    """The first ``frames`` frames of sample ``name`` stepped online with ``modalities``, 120
    particles, ``output.suspect_unpinned_fraction`` = ``suspect``, ``search.rival_every`` and
    ``search.first_frame_rounds`` (None: the config's)."""
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    rounds = cfg.search.first_frame_rounds if first_frame_rounds is None else first_frame_rounds
    cfg = replace(cfg, modalities=modalities, filter=replace(cfg.filter, num_particles=120),
                  output=replace(cfg.output, suspect_unpinned_fraction=suspect),
                  search=replace(cfg.search, rival_every=rival_every, first_frame_rounds=rounds))
    with McapLog(ROOT / "sample_logs" / f"{name}.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        return [estimator.step(frame) for frame, _ in zip(reader, range(frames))]


def test_a_suspect_frame_reports_the_grasp_priors_spread():
    """Once the frames whose evidence left some pose axis open reach the share
    ``output.suspect_unpinned_fraction``, each further frame is flagged ``suspect_estimate`` and its
    covariance holds the grasp prior's whole spread about the estimate on every axis (in place of
    the evidence's widths): the prior's covariance plus the estimate's offset from the nominal grasp,
    squared; the estimates are unchanged."""
    from mvtop_cli.estimator.evidence import evidence_covariance
    from mvtop_cli.estimator.prior import GraspPriorModel

    # the cameras alone cannot see the shaft peg's roll about its long axis; with the first frame's search at 12
    # rounds frame 4 of this draw leaves it open (at the default 10, none of the first 12 frames does)
    plain, watched = (_steps("shaft_peg", ("vision",), 8, suspect, first_frame_rounds=12) for suspect in (None, 0.1))
    cfg = load_config(ROOT / "configs" / "shaft_peg.yaml")
    prior = GraspPriorModel(cfg.grasp_prior, cfg.search.bound)
    prior_var = prior.sigma ** 2
    open_so_far = np.cumsum([not r.evidence.pinned for r in plain])
    assert [r.unpinned for r in watched] == [(int(k), i + 1) for i, k in enumerate(open_so_far)]
    assert 0 < open_so_far[-1] < 8  # this log has both kinds of frame
    for p, w, k in zip(plain, watched, open_so_far):
        np.testing.assert_array_equal(w.T_ee_object, p.T_ee_object)
        assert "suspect_estimate" not in p.flags
        suspect = k / (w.index + 1) >= 0.1
        assert ("suspect_estimate" in w.flags) == suspect
        if suspect:
            assert np.all(np.diag(w.covariance) >= prior_var)
            # (the estimates stay in the nominal grasp's symmetry cell: no fold needed)
            particles = p.covariance - evidence_covariance(p.evidence.likelihood_sigma, prior.sigma,
                                                           cfg.output.evidence_width_factor)
            np.testing.assert_allclose(w.covariance, particles + prior.covariance_about(w.T_ee_object),
                                       rtol=1e-9, atol=1e-15)
            # the axes the frame pinned widen to the prior's spread; an open one had it already
            assert np.all(np.diag(w.covariance) >= np.diag(p.covariance))
            assert np.any(np.diag(w.covariance) > np.diag(p.covariance))
        else:
            np.testing.assert_array_equal(w.covariance, p.covariance)


def test_a_rival_mode_widens_the_covariance_and_changes_no_estimate():
    """The pads alone, pressed flat by the cube's large faces, cannot place it: the rival check
    (every 5th frame) finds another pose millimetres away that explains the frame about as well,
    flags ``rival_mode`` with a warning from that frame on, and the covariance holds the grasp
    prior's spread; the check draws from its own generator, so the estimates are those of a run
    without it. With the cameras too, no rival."""
    from mvtop_cli.estimator.prior import GraspPriorModel

    cfg = load_config(ROOT / "configs" / "cube.yaml")
    prior_var = GraspPriorModel(cfg.grasp_prior, cfg.search.bound).sigma ** 2
    touch = ("tactile", "contact")
    plain, checked = _steps("cube", touch, 10, rival_every=0), _steps("cube", touch, 10, rival_every=5)
    for p, c in zip(plain, checked):
        np.testing.assert_array_equal(c.T_ee_object, p.T_ee_object)
        assert p.rival is None and "rival_mode" not in p.flags
    assert all(c.rival is None and "rival_mode" not in c.flags for c in checked[:4])
    for c in checked[4:]:
        assert "rival_mode" in c.flags and c.rival.frame in (4, 9)
        assert c.rival.nats_below <= cfg.search.rival_margin
        assert c.rival.translation_mm > 1.0 or c.rival.rotation_deg > 3.0
        assert np.all(np.diag(c.covariance) >= prior_var)
    found = [w for c in checked for w in c.warnings if w["kind"] == "rival_mode"]
    assert [w["frame"] for w in found] == [4, 9] and "mm /" in found[0]["detail"]
    both = _steps("cube", ("vision", "tactile", "contact"), 10, rival_every=5)
    assert all(c.rival is None for c in both)


def test_a_rival_stands_until_a_check_finds_the_estimates_own_mode(monkeypatch):
    """A check whose best pose is far away but scores below the margin rules nothing out (the
    earlier rival stands); one whose best pose is the estimate's own mode clears it."""
    from mvtop_cli.filter.health import RivalMode

    rival = RivalMode(1, 2.0, 1.0, 0.5)
    script = iter([(rival, False), (None, False), (None, True)])  # the checks at frames 1, 3 and 5
    monkeypatch.setattr(Estimator, "_rival_check", lambda self, index, likelihood, T: next(script))
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=40),
                  search=replace(cfg.search, rival_every=2, mode_check=False))
    steps = _conn2_steps(cfg, 6)
    assert [s.rival for s in steps] == [None, rival, rival, rival, rival, None]
    assert ["rival_mode" in s.flags for s in steps] == [False, True, True, True, True, False]
    assert [w["frame"] for s in steps for w in s.warnings if w["kind"] == "rival_mode"] == [1]


@pytest.mark.parametrize("rival_gone", [False, True])
def test_a_check_that_finds_the_estimates_own_mode_rules_out_only_a_rival_that_is_gone(monkeypatch, rival_gone):
    """A fresh search of the prior that ends in the estimate's own mode has not shown an earlier
    rival gone: the check also searches around that rival, carried to the estimate, and rules it
    out only when nothing there comes within ``search.rival_margin`` of the estimate. A likelihood
    with two peaks 2 mm apart, the fresh search's poses all at the estimate's: with both peaks as
    high the rival stands; with the rival's peak 50 nats lower it is ruled out."""
    from mvtop_cli.filter.health import RivalMode
    from mvtop_cli.geometry import se3

    cfg = load_config(ROOT / "configs" / "cube.yaml")
    cfg = replace(cfg, modalities=("tactile",), filter=replace(cfg.filter, num_particles=100))
    estimator = Estimator.from_config(cfg)
    T_est = estimator.prior.T_ee_object_nominal
    T_estimate_rival = se3.make_pose(np.eye(3), np.array([0.002, 0.0, 0.0]))
    T_rival = T_est @ T_estimate_rival
    drop = 50.0 if rival_gone else 0.0

    def likelihood(T):  # -(distance to the nearer peak / 0.1 mm)^2, the rival's peak lowered by drop
        to_est = np.linalg.norm(T[:, :3, 3] - T_est[:3, 3], axis=1)
        to_rival = np.linalg.norm(T[:, :3, 3] - T_rival[:3, 3], axis=1)
        return np.maximum(-(to_est / 1e-4) ** 2, -(to_rival / 1e-4) ** 2 - drop)

    at_estimate = np.repeat(T_est[None], 50, axis=0)
    monkeypatch.setattr(Estimator, "_prior_search", lambda self, bounded, rng=None, *a: (at_estimate,
                                                                                        bounded(at_estimate)))
    estimator.rival = RivalMode(3, 2.0, 0.0, 0.0, T_estimate_rival)
    assert estimator._rival_check(5, likelihood, T_est) == (None, rival_gone)


def _conn2_steps(cfg, frames: int) -> list[FrameEstimate]:
    """The first ``frames`` frames of the conn2 sample stepped online with ``cfg``."""
    with McapLog(ROOT / "sample_logs" / "conn2.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        return [estimator.step(frame) for frame, _ in zip(reader, range(frames))]


def _record_rival_checks(monkeypatch) -> list[int]:
    """The frames the rival check runs on, from now on; each finds nothing and rules nothing out."""
    seen: list[int] = []

    def record(self, index, likelihood, T):
        seen.append(index)
        return None, False

    monkeypatch.setattr(Estimator, "_rival_check", record)
    return seen


@pytest.mark.parametrize("beside", [False, True])
def test_where_the_mode_check_searches_it_judges_rivals(monkeypatch, beside):
    """With touch and camera proposals the mode check, on belief-free camera evidence, takes the
    rival check's place (``search.rival_beside_mode_check`` off): its rival stands through a check
    that rules nothing out and goes when one finds the estimate's own mode; a check that could not
    search (no proposals) leaves the frame to the rival check. With the setting on, the rival
    check runs beside it on every checked frame, as before."""
    from mvtop_cli.estimator.estimator import ModeSwitch
    from mvtop_cli.filter.health import RivalMode

    rival = RivalMode(1, 2.0, 1.0, -0.5)
    # the mode checks at frames 1, 3, 5 and 7: a rival; nothing ruled out; the estimate's own mode; no search
    script = iter([(ModeSwitch(rival.warning("scored so, "), rival=rival), False), (None, False), (None, True),
                   (None, None)])
    monkeypatch.setattr(Estimator, "_mode_check", lambda self, frame, result, likelihood, contact: next(script))
    checked = _record_rival_checks(monkeypatch)
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=40),
                  search=replace(cfg.search, rival_every=2, rival_beside_mode_check=beside))
    steps = _conn2_steps(cfg, 8)
    if beside:  # only a rival check that finds the estimate's own mode clears the rival: none here
        assert checked == [1, 3, 5, 7]
        assert [s.rival for s in steps] == [None] + [rival] * 7
    else:
        assert checked == [7]
        assert [s.rival for s in steps] == [None, rival, rival, rival, rival, None, None, None]
    assert [w["frame"] for s in steps for w in s.warnings if w["kind"] == "rival_mode"] == [1]
    assert "scored so, another pose 2.00 mm / 1.00 deg" in steps[1].warnings[-1]["detail"]


@pytest.mark.parametrize("at_contact, checked", [(False, []), (True, [2, 5])])
def test_the_checks_run_at_each_contact_onset_when_set(monkeypatch, at_contact, checked):
    """``search.check_at_contact`` (on by default): the rival (and mode) checks also run on the first frame of
    each contact, a frame in contact after one without (a stalled descent in closed loop),
    not on the frames that stay in contact nor on the first frame."""
    seen = _record_rival_checks(monkeypatch)
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=40),
                  search=replace(cfg.search, rival_every=0, mode_check=False, check_at_contact=at_contact))
    contact = [True, False, True, True, False, True]
    with McapLog(ROOT / "sample_logs" / "conn2.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        for (frame, _), touching in zip(zip(reader, range(6)), contact):
            estimator.step(replace(frame, contact=touching))
    assert seen == checked


def test_a_mode_check_rules_out_the_standing_rival_by_searching_where_it_now_is(monkeypatch):
    """A mode check that finds no rival searches around the standing one, carried along with the
    estimate (``RivalMode.T_estimate_rival``) and spread by the motion noise of the frames since:
    when the best pose there that is still a rival (1 mm / 3 deg from the estimate) scores more
    than ``search.rival_margin`` below the estimate, it is ruled out; within the margin it stands,
    whatever the check's own search found. Poses near the estimate do not count. A held-back switch
    is scored on the check's belief-free terms, any other rival on the frame's likelihood. A rival
    without a pose goes only when the search ends in the estimate's own mode."""
    from mvtop_cli.filter.health import RivalMode
    from mvtop_cli.geometry import se3

    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    estimator = Estimator.from_config(cfg)
    monkeypatch.setattr(estimator.prior, "within", lambda T: np.ones(len(T), dtype=bool))
    margin = cfg.search.rival_margin
    offset = se3.make_pose(np.eye(3), [0.003, 0.0, 0.0])  # the rival: 3 mm along the estimate's x
    T_estimate = se3.make_pose(np.eye(3), [0.01, -0.02, 0.03])  # where the estimate has moved to
    peak = T_estimate @ se3.make_pose(np.eye(3), [0.0035, 0.0002, 0.0])  # the rival's basin, moved by a slip

    def basin(height: float):
        """Log-likelihood: ``height`` at the rival's peak, falling 5 nats per mm away from it, and
        the estimate's own mode (0 nats), a narrow one."""
        def log_likelihood(T):
            near_rival = height - 5.0 * 1e3 * np.linalg.norm(T[:, :3, 3] - peak[:3, 3], axis=1)
            near_estimate = -50.0 * 1e3 * np.linalg.norm(T[:, :3, 3] - T_estimate[:3, 3], axis=1)
            return np.maximum(near_rival, near_estimate)
        return log_likelihood

    ahead, behind = basin(10.0), basin(-margin - 1.0)
    for held in (True, False):
        estimator.rival = RivalMode(9, 3.0, 0.0, 0.5, offset, held=held)
        # scored where it is, the carried pose alone is 2.5 nats below the peak, beyond the margin:
        # the search finds the peak
        for same in (False, True):
            stands = basin(-margin + 1.5)
            free, frame = (stands, behind) if held else (behind, stands)
            assert estimator._rules_out(free, frame, T_estimate, same, 19) is False
            free, frame = (behind, ahead) if held else (ahead, behind)
            assert estimator._rules_out(free, frame, T_estimate, same, 19) is True
    estimator.rival = RivalMode(9, 3.0, 0.0, 0.5)
    assert estimator._rules_out(ahead, ahead, T_estimate, False, 19) is False
    assert estimator._rules_out(ahead, ahead, T_estimate, True, 19) is True
    assert RivalMode(9, 3.0, 0.0, 0.5, offset) == RivalMode(9, 3.0, 0.0, 0.5)  # the pose is not compared


def test_the_tracking_mode_refines_settled_frames_into_fewer_particles():
    """``filter.tracking_particles``: a later frame that is no check frame, keeps the previous
    frame's contact state and follows a frame without an unsettling flag ends with the tracking
    count; the first frame, the check frames and the frame after each of them end with
    ``num_particles`` again. Off (0), every frame keeps ``num_particles``."""
    base = load_config(ROOT / "configs" / "cube.yaml")
    counts, tracked, flags, contact = {}, {}, [], []
    for k in (0, 50):
        cfg = replace(base, filter=replace(base.filter, num_particles=120, tracking_particles=k),
                      search=replace(base.search, rival_every=4))
        with McapLog(ROOT / "sample_logs" / "cube.mcap") as log:
            reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
            estimator = Estimator.from_config(cfg, frame_pose=lambda name, t, tf=reader.tf: tf.lookup("world", name, t))
            counts[k], tracked[k] = [], []
            for frame, _ in zip(reader, range(10)):
                r = estimator.step(frame)
                counts[k].append(len(estimator.particles))
                tracked[k].append(r.timings["tracked"])
                if k:
                    flags.append(set(r.flags))
                    contact.append(frame.contact)
    assert counts[0] == [120] * 10 and not any(tracked[0])
    expected = [False]
    for i in range(1, 10):
        unsettled = flags[i - 1] & {"re_searched", "mode_switch", "rival_mode", "suspect_estimate", "ess_collapsed",
                                    "tempering_forced", "estimate_jump", "sensor_downweighted", "degenerate_weights"}
        expected.append((i + 1) % 4 != 0 and not unsettled and contact[i] == contact[i - 1])
    assert tracked[50] == expected
    assert counts[50] == [50 if t else 120 for t in tracked[50]]
    assert sum(tracked[50]) >= 4 and not tracked[50][3] and not tracked[50][7]
