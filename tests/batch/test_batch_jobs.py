"""The job list of a batch estimate: LOG arguments, folders, glob patterns and manifests; the
names of the output folders; bad input as one line naming the file and row."""

from __future__ import annotations

from pathlib import Path

import pytest

from mvtop_cli.batch.jobs import is_batch_input, jobs_from_arguments, jobs_from_manifest
from mvtop_cli.errors import MvtopError

DEFAULTS = {"modalities": None, "particles": 50, "seed": None, "max_frames": 3}


@pytest.fixture
def tree(tmp_path) -> Path:
    """logs/a.mcap, logs/day2/b.mcap, logs/day2/bag (a rosbag2 folder), logs/notes.txt; cfg.yaml."""
    logs = tmp_path / "logs"
    (logs / "day2" / "bag").mkdir(parents=True)
    (logs / "a.mcap").write_bytes(b"x")
    (logs / "day2" / "b.mcap").write_bytes(b"x")
    (logs / "day2" / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (logs / "day2" / "bag" / "bag_0.mcap").write_bytes(b"x")
    (logs / "notes.txt").write_text("not a log")
    (tmp_path / "cfg.yaml").write_text("{}\n")
    return tmp_path


def test_a_folder_gives_every_log_in_it_named_by_its_relative_path(tree):
    jobs = jobs_from_arguments([str(tree / "logs")], tree / "cfg.yaml", tree / "out", DEFAULTS)
    assert [j.name for j in jobs] == ["a", "day2/b", "day2/bag"]
    assert [Path(j.log) for j in jobs] == [tree / "logs" / "a.mcap", tree / "logs" / "day2" / "b.mcap",
                                           tree / "logs" / "day2" / "bag"]
    assert jobs[1].out == str(tree / "out" / "day2" / "b")
    assert all(j.config == str(tree / "cfg.yaml") and j.particles == 50 and j.max_frames == 3 for j in jobs)


def test_a_glob_pattern_and_several_logs(tree):
    jobs = jobs_from_arguments([str(tree / "logs" / "**" / "*.mcap")], tree / "cfg.yaml", tree / "out", DEFAULTS)
    assert [j.name for j in jobs] == ["a", "b", "bag_0"]
    jobs = jobs_from_arguments([str(tree / "logs" / "a.mcap"), str(tree / "logs" / "day2" / "bag")],
                               tree / "cfg.yaml", tree / "out", DEFAULTS)
    assert [j.name for j in jobs] == ["a", "bag"]


def test_which_single_arguments_mean_a_batch(tree):
    assert is_batch_input(tree / "logs")  # a folder of logs
    assert is_batch_input(str(tree / "logs" / "*.mcap"))
    assert not is_batch_input(tree / "logs" / "a.mcap")
    assert not is_batch_input(tree / "logs" / "day2" / "bag")  # a rosbag2 folder is one log
    assert not is_batch_input(tree / "missing.mcap")


def test_two_logs_with_one_name_are_refused(tree):
    (tree / "other").mkdir()
    (tree / "other" / "a.mcap").write_bytes(b"x")
    with pytest.raises(MvtopError, match=r"two logs would write to .*out/a .*'name' column"):
        jobs_from_arguments([str(tree / "logs" / "a.mcap"), str(tree / "other" / "a.mcap")], tree / "cfg.yaml",
                            tree / "out", DEFAULTS)


def test_patterns_and_folders_without_logs_are_errors(tree):
    with pytest.raises(MvtopError, match=r"nothing\*\.mcap: the pattern matches no log"):
        jobs_from_arguments([str(tree / "nothing*.mcap")], tree / "cfg.yaml", tree / "out", DEFAULTS)
    (tree / "empty").mkdir()
    with pytest.raises(MvtopError, match=r"empty: no log in this folder"):
        jobs_from_arguments([str(tree / "empty")], tree / "cfg.yaml", tree / "out", DEFAULTS)
    with pytest.raises(MvtopError, match=r"needs --config"):
        jobs_from_arguments([str(tree / "logs")], None, tree / "out", DEFAULTS)


def test_csv_manifest_rows_override_the_defaults_and_resolve_paths_from_the_manifest(tree):
    (tree / "run.csv").write_text("log,config,seed,modalities,name\n"
                                  "logs/a.mcap,,7,\"vision,tactile\",first\n"
                                  "logs/day2/b.mcap,cfg.yaml,,,\n")
    jobs = jobs_from_manifest(tree / "run.csv", tree / "default.yaml", tree / "out", DEFAULTS)
    assert [j.name for j in jobs] == ["first", "b"]
    assert jobs[0].config == str(tree / "default.yaml") and jobs[1].config == str(tree / "cfg.yaml")
    assert (jobs[0].seed, jobs[0].modalities) == (7, ("vision", "tactile"))
    assert (jobs[1].seed, jobs[1].modalities, jobs[1].particles) == (None, None, 50)
    assert jobs[0].command() == ["mvtop", "estimate", str(tree / "logs" / "a.mcap"), "--config",
                                 str(tree / "default.yaml"), "--out", str(tree / "out" / "first"),
                                 "--modalities", "vision,tactile", "--particles", "50", "--seed", "7",
                                 "--max-frames", "3"]


def test_yaml_manifest(tree):
    (tree / "run.yaml").write_text("- {log: logs/a.mcap, config: cfg.yaml, modalities: [vision], particles: 20}\n"
                                   "- {log: logs/day2/bag, config: cfg.yaml, seed: 3}\n")
    jobs = jobs_from_manifest(tree / "run.yaml", None, tree / "out", DEFAULTS)
    assert [(j.name, j.modalities, j.particles, j.seed) for j in jobs] == [("a", ("vision",), 20, None),
                                                                          ("bag", None, 50, 3)]


@pytest.mark.parametrize("text, suffix, message", [
    ("log,colour\nlogs/a.mcap,red\n", ".csv", r"run.csv row 1: unknown column 'colour' \(expected log, config"),
    ("log,seed\nlogs/a.mcap,-1\n", ".csv", r"run.csv row 1: seed: expected an integer >= 0, got -1"),
    ("log,modalities\nlogs/a.mcap,sight\n", ".csv", r"run.csv row 1: modalities: expected a comma-separated subset"),
    ("config\ncfg.yaml\n", ".csv", r"run.csv: expected a CSV header row with a 'log' column"),
    ("log\nlogs/a.mcap\n", ".csv", r"run.csv row 1: no config \(expected a 'config' column or --config CFG\)"),
    ("log: a.mcap\n", ".yaml", r"run.yaml: expected a YAML list of mappings"),
    ("log\n", ".txt", r"run.txt: expected a manifest ending in .csv, .yaml or .yml"),
    ("log\n", ".csv", r"run.csv: the manifest lists no log"),
])
def test_bad_manifests_name_the_file_and_row(tree, text, suffix, message):
    path = tree / f"run{suffix}"
    path.write_text(text)
    default_config = None if "no config" in message else tree / "cfg.yaml"
    with pytest.raises(MvtopError, match=message):
        jobs_from_manifest(path, default_config, tree / "out", DEFAULTS)


def test_the_job_key_follows_its_inputs(tree):
    job = jobs_from_arguments([str(tree / "logs" / "a.mcap")], tree / "cfg.yaml", tree / "out", DEFAULTS)[0]
    key = job.key()
    assert job.key() == key
    (tree / "cfg.yaml").write_text("{} # edited\n")
    assert job.key() != key  # another config: the log is estimated again
    other = jobs_from_arguments([str(tree / "logs" / "a.mcap")], tree / "cfg.yaml", tree / "out",
                                {**DEFAULTS, "seed": 1})[0]
    assert other.key() != job.key()
