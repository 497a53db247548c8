"""A batch estimate as Ray tasks on a local Ray instance (2 CPUs): a bad log is a failed row, a
worker killed in the middle of a job is retried by Ray and resumes from its checkpoint, and
every log's outputs equal the serial single-log run. Ray is the optional extra ``mvtop[ray]``
(scripts/setup.sh installs it): without it these tests are skipped, except in CI."""

from __future__ import annotations

import csv
import functools
import os
from pathlib import Path

import pytest
from _batch_logs import assert_same_outputs, kill_worker_after, make_logs, serial_run

from mvtop_cli.batch.engine import RayEngine
from mvtop_cli.batch.run import run_batch
from mvtop_cli.errors import MvtopError

if not os.environ.get("CI"):
    pytest.importorskip("ray")
import ray  # noqa: E402  (in CI a missing ray fails here)


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_no_running_cluster_is_one_line(monkeypatch, tmp_path):
    """``auto`` on a machine where no Ray instance runs. Ray's ``auto`` joins any instance it
    finds on the machine (its processes, or the address file in its temp folder), so the test
    hides those of other programs (another test run) and of this module's fixture, shut down a
    moment ago while its processes exit: an empty temp folder and no process found."""
    if ray.is_initialized():
        ray.shutdown()
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_TMPDIR", str(tmp_path))
    no_process = functools.lru_cache(lambda: [])  # Ray clears the cache of the one it replaces
    monkeypatch.setattr(ray._private.services, "find_gcs_addresses", no_process)
    expected = r"^--ray auto: cannot connect to Ray \(Could not find any running Ray instance"
    with pytest.raises(MvtopError, match=expected):
        list(RayEngine("auto").run(print, [("x",)]))


def test_ray_batch_with_a_bad_log_and_a_killed_worker_equals_the_serial_runs(tmp_path, local_ray):
    jobs = make_logs(tmp_path)
    out = tmp_path / "out"
    killed = kill_worker_after(out / "b", frames=2)
    summary = run_batch(jobs, out, RayEngine("auto"))  # joins the instance the fixture started
    killed["thread"].join(timeout=5)
    assert "pid" in killed, "the worker of log b was not killed before it finished"
    assert (summary["ok"], summary["failed"]) == (2, 1)
    rows = {r["name"]: r for r in csv.DictReader((out / "runs.csv").open())}
    assert rows["bad"]["status"] == "failed" and "truncated MCAP file" in rows["bad"]["error"]
    assert rows["b"]["starts"] == "2" and int(rows["b"]["resumed_at_frame"]) >= killed["frames"]
    assert rows["a"]["starts"] == "1" and rows["a"]["resumed_at_frame"] == "0"
    for job in jobs[:2]:
        assert rows[job.name]["status"] == "ok" and rows[job.name]["frames"] == "6"
        assert_same_outputs(out / job.name, serial_run(job, tmp_path / "serial"))


def test_an_unreachable_cluster_address_is_one_line_not_a_hang():
    """``ray.init`` retries an address nobody listens on for many minutes; the engine checks the
    address first and names it (port 9 on this machine: nothing listens there)."""
    expected = r"^--ray 127\.0\.0\.1:9: cannot reach a Ray cluster there \(.+\); check the address"
    with pytest.raises(MvtopError, match=expected):
        RayEngine("127.0.0.1:9")


def test_an_unreachable_cluster_writes_nothing(tmp_path, capsys):
    """The command stops with the one line and exit code 2 before making its output folder."""
    from mvtop_cli.cli import main

    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "out"
    logs = [str(root / "sample_logs" / f"{name}.mcap") for name in ("cube", "plug")]
    with pytest.raises(SystemExit) as exited:
        main(["estimate", *logs, "--config", str(root / "configs" / "cube.yaml"), "--out", str(out),
              "--ray", "127.0.0.1:9"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.startswith("mvtop: error: --ray 127.0.0.1:9: cannot reach a Ray cluster there (")
    assert not out.exists()
