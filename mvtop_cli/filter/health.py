"""Failure modes of the pose filter, detected per frame: warning records, the jump check
against the motion model, and the per-sensor consistency watch behind eq. 1's weights.

A filter that silently returns a confident wrong pose is worse than none, so every failure
it can detect becomes a warning record ``{"frame": k, "kind": ..., "detail": ...}`` (plus the
numbers behind it), kept in the run's summary and told once per kind on the command line.
The kinds, and what the estimator does about each, are listed in ``WARNING_KINDS`` and in
docs/robustness.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import se3
from .particles import Spread

WARNING_KINDS: dict[str, str] = {
    "degenerate_weights": "no particle had a valid likelihood: the update was skipped",
    "invalid_likelihood": "some likelihood values were NaN or +inf: those particles got weight zero",
    "ess_collapsed": "the effective sample size fell below the collapse threshold: the frame was redone",
    "tempering_forced": "the refinement's budget forced large tempering steps",
    "estimate_jump": "the estimate moved further than the motion model allows",
    "sensor_downweighted": "a sensor disagreed with all the others: its weight was scaled down",
    "mesh_repaired": "a mesh was not watertight or had degenerate faces and was repaired",
    "mesh_open": "an occluder mesh is not watertight (used as it is)",
    "units_suspect": "a mesh's size does not fit the scene: its units may be wrong",
    "contact_grid_coarse": "the contact grid's cells are coarser than the part's clearance",
    "suspect_estimate": "in many frames the evidence did not pin the estimate on some axis, or another pose explained "
                        "it as well: it may be far off",
    "rival_mode": "a fresh search found another pose that explains the frame about as well as the estimate",
    "sensors_disagree": "the sensors contradict each other: without one of them the others prefer another pose by many "
                        "nats, so the estimate rests on that sensor alone",
    "camera_extrinsics": "the known scene lines up with a camera's image only with the camera turned: its "
                         "extrinsics are likely off (corrected, or the run reported suspect)",
    "mode_switch": "with each pose choosing its own camera masks, another pose explained the frame far better: the "
                   "frame was redone from it",
    "mode_held": "with each pose choosing its own camera masks, another pose explained the frame far better, but the "
                 "frames before it since the last contact did not: the estimate stands, the held-back pose a rival "
                 "mode",
}


def warning(frame: int | None, kind: str, detail: str, **numbers) -> dict:
    """One warning record: the frame index (None for the whole run), its kind (a key of
    ``WARNING_KINDS``), a one-sentence detail and any numbers behind it (JSON types)."""
    if kind not in WARNING_KINDS:
        raise ValueError(f"unknown warning kind {kind!r}")
    return {"frame": frame, "kind": kind, "detail": detail, **numbers}


def step_warnings(frame: int, diagnostics: dict, n_particles: int) -> list[dict]:
    """Warnings of one filter update from its ``StepResult.diagnostics`` (see ``pf``):
    degenerate weights, invalid likelihood values, ESS collapse, forced tempering."""
    out = []
    flags = diagnostics.get("flags", ())
    invalid = int(diagnostics.get("invalid_log_likelihood", 0))
    evaluated = int(diagnostics.get("evaluated_poses", 0))
    if "degenerate_weights" in flags:
        out.append(warning(
            frame, "degenerate_weights",
            f"no particle had a finite likelihood ({invalid} of {evaluated} scores NaN or +inf, the rest zero): "
            "the update was skipped and the predicted particles kept",
            invalid=invalid, evaluated=evaluated,
        ))
    elif invalid:
        out.append(warning(
            frame, "invalid_likelihood",
            f"{invalid} of {evaluated} likelihood values were NaN or +inf and counted as weight zero",
            invalid=invalid, evaluated=evaluated,
        ))
    if "ess_collapsed" in flags:
        threshold = float(diagnostics.get("ess_collapse_threshold", 0.0))
        retry = diagnostics.get("collapse_retry")
        if retry is not None:
            before = float(retry["min_ess_before"])
            after = float(diagnostics.get("min_ess", 0.0))
            outcome = "recovered" if retry["recovered"] else "still collapsed"
            detail = (f"effective sample size fell to {before:.1f} of {n_particles} particles (threshold "
                      f"{threshold:.1f}); the frame was redone with {retry['iterations']} tempering iterations: "
                      f"smallest ESS {after:.1f}, {outcome}")
            numbers = {"min_ess": before, "min_ess_after_retry": after, "recovered": bool(retry["recovered"])}
        else:
            before = float(diagnostics.get("min_ess", 0.0))
            detail = (f"effective sample size fell to {before:.1f} of {n_particles} particles "
                      f"(threshold {threshold:.1f})")
            numbers = {"min_ess": before, "recovered": False}
        out.append(warning(frame, "ess_collapsed", detail, threshold=threshold, **numbers))
    elif "tempering_forced" in flags:
        ess = float(diagnostics.get("min_ess", 0.0))
        out.append(warning(
            frame, "tempering_forced",
            f"the refinement's iteration budget forced large tempering steps (smallest ESS {ess:.1f} of {n_particles})",
            min_ess=ess,
        ))
    return out


@dataclass(frozen=True)
class JumpCheck:
    """How far the estimate ``T_ee_object`` moved between two frames against what the
    motion model allows: ``sigmas`` times the RMS spread of the predicted belief (the
    previous belief's covariance plus the motion noise), at least ``sigmas`` times the floor."""

    translation_m: float
    rotation_rad: float
    allowed_translation_m: float
    allowed_rotation_rad: float

    @property
    def jumped(self) -> bool:
        return self.translation_m > self.allowed_translation_m or self.rotation_rad > self.allowed_rotation_rad

    @property
    def ratio(self) -> float:
        """The larger of the two jump / allowance ratios (> 1: jumped)."""
        return max(self.translation_m / self.allowed_translation_m, self.rotation_rad / self.allowed_rotation_rad)


def check_jump(
    previous: Spread,
    estimate: np.ndarray,
    sigma_translation_m: float,
    sigma_rotation_rad: float,
    sigmas: float,
    floor_translation_m: float,
    floor_rotation_rad: float,
) -> JumpCheck:
    """Compare ``estimate`` (4, 4) with the previous frame's belief ``previous`` (mean and
    covariance of ``T_ee_object``), given the motion model's per-axis noise [m] / [rad]
    for this frame (Algorithm 4): the predicted belief's RMS spread is
    ``sqrt(trace(C) + 3 sigma^2)`` in translation and rotation."""
    jump_t = float(np.linalg.norm(estimate[:3, 3] - previous.mean[:3, 3]))
    jump_r = float(se3.rotation_angle(previous.mean[:3, :3], estimate[:3, :3]))
    cov = previous.covariance
    rms_t = float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0) + 3.0 * sigma_translation_m**2))
    rms_r = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0) + 3.0 * sigma_rotation_rad**2))
    return JumpCheck(jump_t, jump_r, sigmas * max(rms_t, floor_translation_m), sigmas * max(rms_r, floor_rotation_rad))


def jump_warning(frame: int, jump: JumpCheck, sigmas: float, cause: str = "") -> dict:
    """The ``estimate_jump`` record of a ``JumpCheck`` that jumped."""
    detail = (f"the estimate moved {1e3 * jump.translation_m:.2f} mm / {np.degrees(jump.rotation_rad):.2f} deg in the "
              f"gripper since the previous frame; the motion model allows {1e3 * jump.allowed_translation_m:.2f} mm / "
              f"{np.degrees(jump.allowed_rotation_rad):.2f} deg ({sigmas:g} sigma of the predicted belief)")
    return warning(
        frame, "estimate_jump", detail + (f" ({cause})" if cause else ""),
        translation_mm=1e3 * jump.translation_m, rotation_deg=float(np.degrees(jump.rotation_rad)),
        allowed_translation_mm=1e3 * jump.allowed_translation_m,
        allowed_rotation_deg=float(np.degrees(jump.allowed_rotation_rad)), ratio=jump.ratio,
    )


@dataclass
class SensorConsistency:
    """Watches, frame by frame, whether each sensor's observed mask agrees with the pose the
    other sensors support, and scales down the eq. 1-2 weight of one that keeps disagreeing
    (a tactile sensor reporting contact nobody else sees, a camera whose masks the others
    contradict; docs/robustness.md says what it cannot see).

    Each frame gives the IoU of every sensor's observed mask with the mask rendered at the
    estimate. A sensor is informative in a frame unless both masks are empty (a tactile
    sensor out of contact agrees trivially). It disagrees when its IoU is below
    ``low_iou`` while at least ``min_others`` other informative, full-weight sensors have a
    median IoU of at least ``consensus_iou``: the others agree on the estimate, it does
    not. After ``frames`` consecutive disagreeing frames (frames where it is not
    informative, or has fewer than ``min_others`` others, neither count nor reset) its
    weight is multiplied by ``factor`` for the rest of the run. At most ``max_fraction`` of
    the sensors are ever scaled down: when more disagree, there is no majority to trust.

    Thresholds: on the five sample logs every sensor's IoU at the estimate is 0.74 or more
    in every frame (medians 0.98-1.0), so 0.5 against a consensus of 0.7 leaves a wide
    margin; five frames (half a second at 10 Hz) keep one bad mask from costing a sensor.
    """

    low_iou: float = 0.5
    consensus_iou: float = 0.7
    frames: int = 5
    factor: float = 0.01
    min_others: int = 2
    max_fraction: float = 0.5
    factors: dict[str, float] = field(default_factory=dict)
    streak: dict[str, int] = field(default_factory=dict)  # every sensor seen: consecutive disagreeing frames

    def reset(self) -> None:
        """Forget every verdict (factors and streaks): they judged the sensors against an
        estimate found to be in a wrong mode (``mode_switch``)."""
        self.factors.clear()
        self.streak.clear()

    def weight_factor(self, name: str) -> float:
        """The factor (1 or ``factor``) applied to sensor ``name``'s weight."""
        return self.factors.get(name, 1.0)

    def disagreeing(self, ious: dict[str, float], informative: dict[str, bool]) -> dict[str, float | None]:
        """One frame's verdict per informative sensor with at least ``min_others`` informative,
        full-weight others: the others' median IoU when the sensor disagrees with the estimate
        they agree on (its IoU below ``low_iou``, theirs at least ``consensus_iou``), else
        None. Sensors without such others are left out (the frame says nothing of them)."""
        trusted = [n for n in ious if informative.get(n, False) and self.weight_factor(n) == 1.0]
        out: dict[str, float | None] = {}
        for name in ious:
            if not informative.get(name, False):
                continue
            others = [ious[n] for n in trusted if n != name]
            if len(others) < self.min_others:
                continue
            med = float(np.median(others))
            out[name] = med if ious[name] < self.low_iou and med >= self.consensus_iou else None
        return out

    def observe(self, ious: dict[str, float], informative: dict[str, bool]) -> list[tuple[str, float, float]]:
        """Take one frame's IoUs at the estimate (by sensor name) and which sensors were
        informative; returns ``(name, its IoU, the others' median IoU)`` of the sensors
        scaled down in this frame (usually none)."""
        for name in ious:
            self.streak.setdefault(name, 0)
        newly = []
        for name, med in self.disagreeing(ious, informative).items():
            if med is None:
                self.streak[name] = 0
                continue
            self.streak[name] += 1
            if self.weight_factor(name) != 1.0 or self.streak[name] < self.frames:
                continue
            if len(self.factors) + 1 > self.max_fraction * len(self.streak):
                continue
            self.factors[name] = self.factor
            newly.append((name, float(ious[name]), med))
        return newly


def sensor_report(frames: list[tuple[int, dict[str, float]]], warnings: list[dict]) -> dict:
    """Per sensor over a run: the median and smallest IoU of its observed mask at the
    estimate, the frames it was seen in, and its weight factor with the frame it was scaled
    down at (from the ``sensor_downweighted`` records). ``frames``: (index, IoU by sensor)."""
    out: dict[str, dict] = {}
    for _, ious in frames:
        for name, v in ious.items():
            out.setdefault(name, {"iou": []})["iou"].append(v)
    report = {}
    for name, rec in out.items():
        iou = np.asarray(rec["iou"])
        report[name] = {
            "frames": len(iou),
            "median_iou_at_estimate": round(float(np.median(iou)), 4),
            "min_iou_at_estimate": round(float(iou.min()), 4),
            "weight_factor": 1.0,
            "downweighted_at_frame": None,
        }
    for w in warnings:
        if w["kind"] == "sensor_downweighted" and w["sensor"] in report:
            report[w["sensor"]].update(weight_factor=w["weight_factor"], downweighted_at_frame=w["frame"])
    return report


def count_warnings(warnings: list[dict]) -> dict[str, int]:
    """Number of records per kind (for per-frame kinds: the number of frames)."""
    counts: dict[str, int] = {}
    for w in warnings:
        counts[w["kind"]] = counts.get(w["kind"], 0) + 1
    return counts


@dataclass(frozen=True)
class RivalMode:
    """What a frame's rival check found (``search.rival_every``): the best pose of a fresh search
    of the grasp prior lies ``translation_mm`` / ``rotation_deg`` from the estimate (modulo the
    part's symmetries) and scores ``nats_below`` under it (negative: above it) at ``frame``.
    ``T_estimate_rival`` (4, 4), when known, is that pose in the estimate's object frame, so a
    later check can score the same hypothesis where the estimate has moved to. ``held``: the
    mode check's belief-free evidence put it ahead of the estimate by more than
    ``search.mode_margin`` and only the earlier frames held the switch back (``mode_held``).
    ``sensor``: the sensors disagree (``search.disagreement_margin``): without that sensor's
    term the others prefer this pose to the estimate by ``others_gain`` nats, so the estimate
    rests on that one sensor's word against theirs (warning ``sensors_disagree``)."""

    frame: int
    translation_mm: float
    rotation_deg: float
    nats_below: float
    T_estimate_rival: np.ndarray | None = field(default=None, compare=False, repr=False)
    held: bool = False
    sensor: str | None = None
    others_gain: float | None = None

    def warning(self, scored: str = "") -> dict:
        """The frame's ``rival_mode`` (with ``sensor``: ``sensors_disagree``) warning record;
        ``scored`` opens its sentence with how the poses were scored when not by the frame's
        likelihood (the mode check's terms)."""
        until = "until a later check rules it out" if self.sensor is None else "for the rest of the run"
        return warning(
            self.frame, self.kind,
            f"{scored}another pose {self.translation_mm:.2f} mm / {self.rotation_deg:.2f} deg from the estimate "
            f"explains the sensors {self.comparison}: {until}, the covariance is the grasp prior's spread about the "
            "estimate",
            translation_mm=self.translation_mm, rotation_deg=self.rotation_deg, nats_below=self.nats_below,
            ratio=-self.nats_below if self.sensor is None else self.others_gain,
            **({} if self.sensor is None else {"sensor": self.sensor, "others_gain": self.others_gain}),
        )

    @property
    def kind(self) -> str:
        """Its warning kind and flag: ``sensors_disagree`` with a ``sensor``, else ``rival_mode``."""
        return "rival_mode" if self.sensor is None else "sensors_disagree"

    @property
    def comparison(self) -> str:
        """How the rival scores against the estimate, in words."""
        if self.sensor is not None:
            return (f"other than {self.sensor!r} {self.others_gain:.1f} nats better than the estimate does "
                    f"({self.sensor!r} alone holds the estimate there)")
        if round(self.nats_below, 1) >= 0:  # a lead that rounds to 0.0 is no lead in words
            return f"within {abs(self.nats_below):.1f} nats of it"
        return f"{-self.nats_below:.1f} nats better than it"


def left_open(pinned: bool, rival: RivalMode | None) -> bool:
    """Whether a frame with evidence left the pose open: some axis (``EvidenceReport.pinned``
    False) or another mode (a rival the checks found and none has ruled out yet). The
    ``suspect_estimate`` share counts such frames."""
    return not pinned or rival is not None


def is_suspect(open_frames: int, frames: int, max_unpinned_fraction: float | None) -> bool:
    """Whether ``open_frames`` of ``frames`` frames with evidence, those that left the pose open
    (``left_open``), make up at least ``max_unpinned_fraction`` of them
    (``output.suspect_unpinned_fraction``; None: never)."""
    return max_unpinned_fraction is not None and frames > 0 and open_frames / frames >= max_unpinned_fraction


def suspect_warning(closed: list[bool], max_unpinned_fraction: float | None,
                    rival: RivalMode | None = None) -> dict | None:
    """The run's ``suspect_estimate`` record, or None: raised when the frames that left the pose
    open (``closed`` False, one entry per frame with evidence: ``not left_open``) make up at least
    ``max_unpinned_fraction`` of them (None: never raised), or when ``rival`` still stands at the
    end. The share sees a wrong mode the cameras leave open (e.g. a part they see mostly behind
    the fingers), and one a rival stood against for much of the run before a check, scoring on
    masks the belief chose, ruled it out; not one every sensor explains (README: The
    suspect_estimate warning)."""
    open_frames = sum(not p for p in closed)
    if not is_suspect(open_frames, len(closed), max_unpinned_fraction):
        if rival is None:
            return None
        return warning(
            None, "suspect_estimate",
            f"at frame {rival.frame} another pose {rival.translation_mm:.2f} mm / {rival.rotation_deg:.2f} deg from "
            f"the estimate explained the sensors {rival.comparison}, and no later check ruled it out: the "
            "estimate may be either; its covariance is the grasp prior's spread about it "
            f"(flag {rival.kind}); check it against another "
            "measurement before relying on it",
            rival_frame=rival.frame, rival_translation_mm=rival.translation_mm, rival_rotation_deg=rival.rotation_deg,
        )
    fraction = open_frames / len(closed)
    return warning(
        None, "suspect_estimate",
        f"the evidence left some pose axis or a rival mode open in {open_frames} of {len(closed)} frames "
        f"({100 * fraction:.0f} %, threshold {100 * max_unpinned_fraction:.0f} %): the estimate may be far off; from "
        "the frame this share was reached its covariance is the grasp prior's spread about it (flag "
        "suspect_estimate); check it against another measurement before relying on it",
        unpinned_frames=open_frames, frames=len(closed), unpinned_fraction=fraction,
    )


SUSPECT_CAUSES = ("unpinned", "rival_mode", "sensors_disagree", "camera_extrinsics")


def suspect_causes(closed: list[bool], max_unpinned_fraction: float | None, rivals: list[RivalMode | None],
                   camera_left_turned: bool) -> dict:
    """Why a run ends suspect: every reason for its ``suspect_estimate`` record that holds at
    its end, not only the one its sentence gives (summary.json ``suspect``, kept by the
    benchmark, so another ``output.suspect_unpinned_fraction`` can be judged from finished runs).
    ``closed`` one entry per frame with evidence (``not left_open``; cause ``unpinned``: the
    share of open frames); ``rivals`` the rival mode and the first frame's sensor disagreement
    still standing (None: none); ``camera_left_turned`` a camera whose extrinsics look off was
    used as recorded. ``causes`` is a subset of ``SUSPECT_CAUSES`` in that order; the record is
    raised when it is not empty."""
    open_frames = sum(not p for p in closed)
    causes = ["unpinned"] if is_suspect(open_frames, len(closed), max_unpinned_fraction) else []
    causes += [k for k in SUSPECT_CAUSES[1:3] if any(r is not None and r.kind == k for r in rivals)]
    if camera_left_turned:
        causes.append("camera_extrinsics")
    return {"raised": bool(causes), "causes": causes, "unpinned_frames": open_frames, "evidence_frames": len(closed),
            "unpinned_threshold": max_unpinned_fraction}


def warning_lines(warnings: list[dict], frames_processed: int) -> list[str]:
    """One line per kind for the terminal: how many frames (which, up to five) and the
    detail of the worst case (the largest ``ratio`` where records have one, else the first)."""
    by_kind: dict[str, list[dict]] = {}
    for w in warnings:
        by_kind.setdefault(w["kind"], []).append(w)
    lines = []
    for kind, records in by_kind.items():
        worst = max(records, key=lambda r: r.get("ratio", 0.0))
        frames = [r["frame"] for r in records if r["frame"] is not None]
        if frames:
            shown = ", ".join(str(f) for f in frames[:5]) + (", ..." if len(frames) > 5 else "")
            where = f"in {len(frames)} of {frames_processed} frames ({shown})"
            lead = "worst: " if len(records) > 1 else ""
            lines.append(f"{kind} {where}: {lead}{worst['detail']}")
        else:
            lines.extend(f"{kind}: {r['detail']}" for r in records)
    return lines
