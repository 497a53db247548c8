"""When each simulated sensor captures an image: rates, dropped frames and stamp jitter.

Real setups do not trigger their sensors together: cameras may run slower than the tactile
sensors, drivers drop images, and each sensor exposes at its own time near the nominal one.
The schedule says, per frame and sensor, at which time [ns] the sensor captures (the image
then shows the scene at that time and carries it as its header stamp), or None when the
sensor publishes nothing in that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorTiming:
    """``camera_every``: cameras capture on every n-th frame only (2: half the tactile rate);
    ``drop_fraction``: probability that any one image (camera, or tactile image with its
    depth) is lost; ``jitter_s``: each capture lies uniformly within +-``jitter_s`` [s] of
    its frame's nominal time."""

    camera_every: int = 1
    drop_fraction: float = 0.0
    jitter_s: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.camera_every, (int, np.integer)) and self.camera_every >= 1):
            raise ValueError(f"camera_every must be an integer >= 1, got {self.camera_every!r}")
        if not 0.0 <= self.drop_fraction < 1.0:
            raise ValueError(f"drop_fraction must be in [0, 1), got {self.drop_fraction!r}")
        if not (np.isfinite(self.jitter_s) and self.jitter_s >= 0.0):
            raise ValueError(f"jitter_s must be finite and >= 0 s, got {self.jitter_s!r}")

    @property
    def is_default(self) -> bool:
        """True when every sensor captures at every frame's nominal time."""
        return self.camera_every == 1 and self.drop_fraction == 0.0 and self.jitter_s == 0.0


def capture_schedule(
    stamps_ns: list[int],
    sensors: list[tuple[str, str]],
    timing: SensorTiming,
    rng: np.random.Generator,
) -> list[dict[str, int | None]]:
    """Capture time [ns] (or None: nothing published) per frame and sensor.

    stamps_ns : the frames' nominal times [ns], increasing.
    sensors : ``(name, modality)`` pairs, modality ``camera`` or ``tactile``.
    rng draws, frame by frame and sensor by sensor, whether the image is dropped and its
    time offset; a default ``timing`` draws nothing and returns the nominal times.
    """
    if len(stamps_ns) > 1 and 2 * timing.jitter_s * 1e9 >= float(np.min(np.diff(stamps_ns))):
        raise ValueError(
            f"stamp jitter +-{timing.jitter_s} s overlaps neighbouring frames "
            f"(period {float(np.min(np.diff(stamps_ns))) / 1e9} s)"
        )
    out: list[dict[str, int | None]] = []
    for k, t in enumerate(stamps_ns):
        frame: dict[str, int | None] = {}
        for name, modality in sensors:
            if timing.is_default:
                frame[name] = int(t)
                continue
            dropped = rng.random() < timing.drop_fraction
            offset_ns = int(round(rng.uniform(-timing.jitter_s, timing.jitter_s) * 1e9))
            off_rate = modality == "camera" and k % timing.camera_every != 0
            frame[name] = None if (dropped or off_rate) else int(t) + offset_ns
        out.append(frame)
    return out
