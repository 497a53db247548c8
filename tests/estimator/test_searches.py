"""The estimator's searches of the grasp prior: the first frame's runs ``search.first_frame_rounds``
rounds, the rival check's ``search.rounds``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mvtop_cli.estimator.estimator as estimator_module
from mvtop_cli.config import load_config
from mvtop_cli.estimator import Estimator
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

ROOT = Path(__file__).resolve().parents[2]


def test_the_first_frame_and_the_rival_check_search_with_their_own_rounds(monkeypatch):
    calls = []
    search = estimator_module.cross_entropy_search

    def spy(initial, log_likelihood, rng, **kwargs):
        calls.append((len(initial), kwargs["rounds"]))
        return search(initial, log_likelihood, rng, **kwargs)

    monkeypatch.setattr(estimator_module, "cross_entropy_search", spy)
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    # the rival check on frame 1 (rival_every 2), the mode check off so that it runs
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=40),
                  search=replace(cfg.search, first_frame_rounds=3, rounds=5, rival_every=2, mode_check=False,
                                 dissent=False))
    with McapLog(ROOT / "sample_logs" / "conn2.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        for frame, _ in zip(reader, range(2)):
            estimator.step(frame)
    population = 40 * cfg.search.init_factor
    assert calls == [(population, 3), (population, 5)]
