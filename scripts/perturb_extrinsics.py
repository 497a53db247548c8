"""Copy a log with one camera's extrinsics turned: every /tf_static transform whose child is
FRAME is rotated by DEG degrees about its own AXIS (x, y or z of that frame) and, with --shift-mm,
moved along its own axes, the rest of the log copied unchanged. For checking what a miscalibrated
camera does to an estimate (README: How far to trust the reported covariance; docs/robustness.md).

Usage: .venv/bin/python scripts/perturb_extrinsics.py LOG OUT FRAME DEG [--axis y] [--shift-mm X,Y,Z]
e.g.   scripts/perturb_extrinsics.py sample_logs/cube.mcap /tmp/cube_front2.mcap front_optical 2
"""

import argparse
from pathlib import Path

import numpy as np

from mvtop_cli.geometry import se3
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter
from mvtop_cli.io.tf_buffer import stamp_to_ns


def perturb_log(log_path: Path, out_path: Path, frame: str, turn: np.ndarray) -> int:
    """Copy ``log_path`` to ``out_path`` with every /tf_static transform whose child is ``frame``
    multiplied by ``turn`` (4, 4) on the right (in that frame's own axes); returns how many were."""
    turned = 0
    with McapLog(log_path) as log, LogWriter(out_path) as out:
        types = {t.name: t.type for t in log.summary().topics}
        static = iter([m.msg for m in log.messages("/tf_static")])  # decoded, in the same order as below
        for m in log.messages(decode=False):
            if m.topic != "/tf_static":
                out.write_raw(m.topic, types[m.topic], m.msg, m.log_time_ns, m.publish_time_ns)
                continue
            tf = next(static)
            items = []
            for t in tf.transforms:
                tr, q = t.transform.translation, t.transform.rotation
                T = se3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]), np.array([tr.x, tr.y, tr.z]))
                if t.child_frame_id.lstrip("/") == frame:
                    T, turned = T @ turn, turned + 1
                items.append((t.header.frame_id, t.child_frame_id, T))
            out.write_tf(items, stamp_to_ns(tf.transforms[0].header.stamp), static=True, log_time_ns=m.log_time_ns)
    return turned


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("frame")
    ap.add_argument("deg", type=float)
    ap.add_argument("--axis", choices=("x", "y", "z"), default="y")
    ap.add_argument("--shift-mm", default="0,0,0", help="move the frame along its own x, y, z axes [mm]")
    a = ap.parse_args()
    turn = np.eye(4)
    turn[:3, :3] = se3.rotvec_to_matrix(np.radians(a.deg) * np.eye(3)["xyz".index(a.axis)])
    turn[:3, 3] = 1e-3 * np.array([float(v) for v in a.shift_mm.split(",")])
    turned = perturb_log(a.log, a.out, a.frame, turn)
    if not turned:
        a.out.unlink()
        raise SystemExit(f"{a.log}: no /tf_static transform has child frame {a.frame!r}")
    print(f"wrote {a.out}: {a.frame} turned {a.deg:g} deg about its {a.axis} axis, moved {a.shift_mm} mm "
          f"({turned} transforms)")


if __name__ == "__main__":
    main()
