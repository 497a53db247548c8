"""How the camera extrinsics check (`extrinsics`, README: Cameras whose extrinsics are off) falls
on simulated grasps: per object and grasp, the log simulated with 4 frames (its first frame is that
of the benchmark's 30-frame log of the same seed), each camera checked on its first image
(`estimator.extrinsics.check_camera`) as recorded and, with --turn, with that camera turned by a
random angle (uniform in --turn-deg) about a random axis of its optical frame (drawn from the grasp's
seed and the camera's name). Prints the calibrated cameras judged misaligned (false alarms), the
turned ones found, and how far the found turn is from the true one; --rows appends one JSON line
per grasp (resumable: grasps already there are skipped; gzip-compressed when ROWS ends in .gz).
Usage: .venv/bin/python scripts/extrinsics_check.py --scene default|hard --rows ROWS.jsonl
       [--objects cube,...] [--seeds 1000-1099] [--turn] [--turn-deg 1,3]"""
import argparse
import gzip
import json
import tempfile
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.estimator.extrinsics import check_camera
from mvtop_cli.estimator.scene import SceneModel
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.simulate import SimulateOptions, scene_options, simulate, write_scene_config
from mvtop_cli.records import Frame
from mvtop_cli.sim.episode import EpisodeOptions


def random_turn(seed: int, camera: str, lo_deg: float, hi_deg: float) -> np.ndarray:
    """A rotation vector (3,) [deg]: an angle uniform in [lo, hi] about a uniformly random axis."""
    rng = np.random.default_rng([seed, zlib.crc32(camera.encode())])
    axis = rng.normal(size=3)
    return rng.uniform(lo_deg, hi_deg) * axis / np.linalg.norm(axis)


def turned(frame: Frame, camera: str, turn_deg: np.ndarray) -> Frame:
    """``frame`` with camera ``camera``'s recorded pose turned about its optical centre by ``turn_deg``
    (``T_world_sensor @ Exp(turn)``, as scripts/perturb_extrinsics.py turns a log's): the check should
    find ``turn_deg``."""
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_matrix(np.radians(turn_deg))
    img = frame.cameras[camera]
    return replace(frame, cameras={**frame.cameras, camera: replace(img, T_world_sensor=img.T_world_sensor @ T)})


def check_grasp(obj: str, seed: int, scene: str, turn: tuple[float, float] | None) -> dict:
    """Per camera: the check on the first image as recorded and (with ``turn``) turned."""
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "log.mcap"
        simulate(obj, seed, log, scene_options(SimulateOptions(episode=EpisodeOptions(frames=4)), scene))
        cfg = load_config(write_scene_config(obj, Path(d) / "config.yaml"))
        model = SceneModel(cfg, build_contact=False)
        with McapLog(log) as opened:
            reader = FrameReader(opened, sensor_topics(cfg), log_topics(cfg))
            frame = next(iter(reader))
            out = {}
            for name in frame.cameras:
                row = {}
                cases = [("recorded", np.zeros(3))] + ([("turned", random_turn(seed, name, *turn))] if turn else [])
                for case, t in cases:
                    img = turned(frame, name, t).cameras[name]
                    a = check_camera(model, name, img, frame.index,
                                     lambda f, img=img: reader.tf.lookup(cfg.frames.world, f, img.stamp_ns),
                                     cfg.extrinsics)
                    row[case] = {"true_turn_deg": t.round(4).tolist(), **({"judged": False} if a is None else {
                        "judged": True, "turn_deg": list(a.turn_deg), "gain": a.gain, "samples": a.samples,
                        "misaligned": a.misaligned, "at_edge": a.at_edge, "mesh_spread_deg": a.mesh_spread_deg,
                        "corrected": a.corrected})}
                out[name] = row
    return out


def resumable_rows(path: Path, objects: str, seeds: str, make_row) -> dict:
    """The rows of ``path`` (JSON lines, gzip-compressed when it ends in .gz) by (object, seed),
    with ``make_row(object, seed)`` appended for every object of ``objects`` and seed of ``seeds``
    ("A-B") not there yet, seed by seed."""
    opener = gzip.open if path.suffix == ".gz" else open
    rows = {}
    if path.exists():
        with opener(path, "rt") as f:
            for line in f:
                r = json.loads(line)
                rows[(r["object"], r["seed"])] = r
    a, b = (int(x) for x in seeds.split("-"))
    for seed in range(a, b + 1):
        for obj in objects.split(","):
            if (obj, seed) in rows:
                continue
            rows[(obj, seed)] = row = make_row(obj, seed)
            with opener(path, "at") as f:
                f.write(json.dumps(row) + "\n")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", required=True, choices=("default", "hard"))
    ap.add_argument("--rows", type=Path, required=True)
    ap.add_argument("--objects", default="cube,shaft_peg,plug,conn1,conn2")
    ap.add_argument("--seeds", default="1000-1099")
    ap.add_argument("--turn", action="store_true")
    ap.add_argument("--turn-deg", default="1,3")
    args = ap.parse_args()
    turn = tuple(float(x) for x in args.turn_deg.split(",")) if args.turn else None
    rows = resumable_rows(args.rows, args.objects, args.seeds, lambda obj, seed: {
        "object": obj, "seed": seed, "scene": args.scene, "cameras": check_grasp(obj, seed, args.scene, turn)})
    cams = [c for r in rows.values() for c in r["cameras"].values()]
    rec = [c["recorded"] for c in cams]
    judged = [c for c in rec if c["judged"]]
    print(f"{len(rows)} grasps, {len(rec)} cameras as recorded: {len(judged)} judged, "
          f"{sum(c['misaligned'] for c in judged)} misaligned (false alarms); largest turn found "
          f"{max(np.linalg.norm(c['turn_deg']) for c in judged):.3f} deg, largest gain "
          f"{max(c['gain'] for c in judged):.3f}")
    tur = [c["turned"] for c in cams if "turned" in c and c["turned"]["judged"]]
    if tur:
        err = [np.linalg.norm(np.subtract(c["turn_deg"], c["true_turn_deg"])) for c in tur]
        spread = [c["mesh_spread_deg"] for c in tur if c["misaligned"]]
        print(f"turned {turn[0]:g}-{turn[1]:g} deg: {len(tur)} judged, {sum(c['misaligned'] for c in tur)} found "
              f"misaligned, {sum(c['corrected'] for c in tur)} corrected, {sum(c['at_edge'] for c in tur)} at the "
              f"range's edge; found turn off the true one by median {np.median(err):.3f} deg, max {max(err):.3f} deg; "
              f"smallest gain {min(c['gain'] for c in tur):.3f}; meshes' own turns apart by median "
              f"{np.median(spread):.3f} deg, max {max(spread):.3f} deg")


if __name__ == "__main__":
    main()
