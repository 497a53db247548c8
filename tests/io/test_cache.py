"""The cache folder: ``MVTOP_CACHE_DIR``, off when empty, else the XDG cache; the scene's
contact grid is stored there once and read back the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvtop_cli.io.cache import cache_dir

ROOT = Path(__file__).resolve().parents[2]


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("MVTOP_CACHE_DIR", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c"
    monkeypatch.setenv("MVTOP_CACHE_DIR", "")
    assert cache_dir() is None
    monkeypatch.delenv("MVTOP_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "mvtop"


def test_the_scene_keeps_its_contact_grid_in_the_cache(monkeypatch, tmp_path):
    from mvtop_cli.config import load_config
    from mvtop_cli.estimator.scene import SceneModel

    cfg = load_config(ROOT / "configs" / "cube.yaml")
    monkeypatch.setenv("MVTOP_CACHE_DIR", "")
    uncached = SceneModel(cfg)
    assert not any(tmp_path.iterdir())
    monkeypatch.setenv("MVTOP_CACHE_DIR", str(tmp_path))
    first, second = SceneModel(cfg), SceneModel(cfg)
    assert len(list(tmp_path.glob("env_sdf_*.npz"))) == 1
    for scene in (first, second):
        np.testing.assert_array_equal(scene.sdf.env_sdf.values, uncached.sdf.env_sdf.values)
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, 3] = np.random.default_rng(0).normal(scale=0.01, size=(5, 3)) + uncached.sdf.env_sdf.bounds.mean(axis=0)
    np.testing.assert_array_equal(second.phi(T), uncached.phi(T))
