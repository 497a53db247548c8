"""Where a batch's jobs run: ``LocalEngine`` (this process, or a pool of worker processes on
this machine) or ``RayEngine`` (Ray tasks on a local Ray instance or a cluster).

An engine runs ``fn(*args)`` for each of a list of argument tuples and yields
``Outcome(index, value, error)`` in completion order. ``fn`` must be a module-level function
(workers import it by name: on a Ray cluster every node needs mvtop installed, the same
version). Each job's numba kernels use ``threads`` threads, so that ``workers x threads``
matches the machine's cores (the tracks do not depend on the thread count).

A worker process that dies in the middle of a job (killed, out of memory, a crash in native
code) has its job run again, up to ``max_retries`` times: Ray retries the task on any live
worker (its task retries); a local job runs in a process of its own, started again. An
exception raised by ``fn`` is not retried: it is the job's outcome.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import re
import signal
import socket
import sys
from dataclasses import dataclass
from multiprocessing import forkserver
from multiprocessing.connection import wait as mp_wait
from typing import Any, Callable, Iterator

from ..errors import MvtopError

# Runs of a job whose worker died before the job's outcome is given up (the first run included:
# Ray's max_retries counts the retries only).
MAX_RETRIES = 3
# Seconds between two looks at the finished Ray tasks (the driver sleeps in between).
_RAY_WAIT_S = 0.5
# Seconds to wait for a Ray cluster's address to accept a connection before giving up (ray.init
# itself retries an unreachable address for many minutes).
_RAY_CONNECT_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class Outcome:
    """A job's result: ``value`` from ``fn``, or ``error`` (its exception, or the reason its
    worker did not return)."""

    index: int
    value: Any = None
    error: BaseException | None = None


def thread_environment(threads: int) -> dict[str, str]:
    """Thread counts of the numeric libraries, read once when they load: numba, and OpenMP and
    OpenBLAS (left at all cores in a worker sharing the machine, their idle threads spin: an
    estimate with one numba thread took 1.5x the CPU time, 17.4 s instead of 11.8 s for 10
    plug frames)."""
    n = str(threads)
    return {"NUMBA_NUM_THREADS": n, "OMP_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n}


@contextlib.contextmanager
def _environment(values: dict[str, str]):
    """``os.environ`` with ``values`` while the body runs."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def set_threads(threads: int) -> None:
    """Limit this process's numba kernels to ``threads`` threads (before or after numba starts
    its thread pool; never more than the pool has)."""
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def call_with_threads(fn: Callable, threads: int, args: tuple) -> Any:
    """``fn(*args)`` with ``threads`` numba threads: what a worker runs for each job."""
    set_threads(threads)
    return fn(*args)


class LocalEngine:
    """``workers`` processes on this machine (1: the jobs run one after the other in this
    process), each job with ``cpu_count // workers`` numba threads."""

    def __init__(self, workers: int = 1, max_retries: int = MAX_RETRIES):
        self.workers = max(1, int(workers))
        self.max_retries = max_retries
        self.threads = max(1, (os.cpu_count() or 1) // self.workers)

    def describe(self) -> str:
        return f"{self.workers} local worker{'s' if self.workers > 1 else ''}"

    def run(self, fn: Callable, arglist: list[tuple]) -> Iterator[Outcome]:
        if self.workers == 1:
            for i, args in enumerate(arglist):
                try:
                    yield Outcome(i, fn(*args))
                except Exception as err:
                    yield Outcome(i, error=err)
            return
        yield from self._run_processes(fn, arglist)

    def _run_processes(self, fn: Callable, arglist: list[tuple]) -> Iterator[Outcome]:
        """One process per job, ``workers`` at a time; a process that ends without sending its
        outcome died, and its job is started again (at most ``max_retries`` runs). The processes
        are forked from a fork server that has imported ``fn``'s module (cheap starts, and safe
        whatever this process did: forking a process whose OpenMP threads run is not)."""
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload([fn.__module__])
        with _environment(thread_environment(self.threads)):  # the fork server's, so every worker's
            forkserver.ensure_running()
        queue = list(range(len(arglist)))
        runs = [0] * len(arglist)
        live: dict[int, tuple[Any, Any]] = {}  # index -> (process, receiving end)
        try:
            while queue or live:
                while queue and len(live) < self.workers:
                    i = queue.pop(0)
                    recv, send = ctx.Pipe(duplex=False)
                    proc = ctx.Process(target=_child, args=(send, fn, self.threads, arglist[i]), daemon=True)
                    proc.start()
                    send.close()
                    runs[i] += 1
                    live[i] = (proc, recv)
                ready = mp_wait([c for _, c in live.values()] + [p.sentinel for p, _ in live.values()])
                for i in [i for i, (p, c) in live.items() if c in ready or p.sentinel in ready]:
                    proc, recv = live.pop(i)
                    message = None
                    try:
                        message = recv.recv()
                    except (EOFError, OSError):
                        pass
                    recv.close()
                    proc.join()
                    if message is not None:
                        yield Outcome(i, message[1]) if message[0] == "ok" else Outcome(i, error=message[1])
                    elif runs[i] >= self.max_retries:
                        yield Outcome(i, error=MvtopError(
                            f"its worker process died {runs[i]} times (last exit code {proc.exitcode})"))
                    else:
                        queue.insert(0, i)
        finally:
            for proc, recv in live.values():  # interrupted: the jobs stop (their checkpoints stay)
                if proc.is_alive():
                    proc.terminate()
                proc.join(timeout=30)
                recv.close()


def _child(send, fn: Callable, threads: int, args: tuple) -> None:
    """A local worker process: run one job, send ("ok", value) or ("error", exception). SIGTERM
    (the driver stopping) stops the job like Ctrl-C: it cleans up and the process exits."""
    from ..pipelines.checkpoint import Terminated

    def stop(signum: int, _frame) -> None:
        raise Terminated(signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        message = ("ok", call_with_threads(fn, threads, args))
    except Exception as err:  # the job's outcome
        message = ("error", err)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the job stops (leaving its checkpoint), quietly
        sys.exit(130)
    gone = (BrokenPipeError, ConnectionResetError)  # the parent is gone (stopped): nobody to tell, quietly
    try:
        send.send(message)
    except gone:
        pass
    except Exception as err:  # an unpicklable value or exception
        with contextlib.suppress(*gone):
            send.send(("error", MvtopError(f"{type(err).__name__}: {err}")))
    finally:
        send.close()


class RayEngine:
    """Ray tasks, one per job, each asking for ``cpus_per_job`` CPUs and running numba with
    as many threads. ``address``: ``local`` starts a private Ray instance on this machine
    with ``num_cpus`` CPUs (default: all), ``auto`` joins the cluster this machine is part of
    (``ray start``; or RAY_ADDRESS), anything else is a cluster address (``HOST:PORT`` or
    ``ray://HOST:PORT``)."""

    def __init__(self, address: str, num_cpus: int | None = None, cpus_per_job: int = 1,
                 max_retries: int = MAX_RETRIES):
        # an address nobody listens on: one line now, before any output is written
        _check_reachable(address if address != "auto" else os.environ.get("RAY_ADDRESS", "auto"))
        self.address = address
        self.num_cpus = num_cpus
        self.cpus_per_job = cpus_per_job
        self.max_retries = max_retries
        self.threads = cpus_per_job
        self._started = False

    def describe(self) -> str:
        if self.address == "local":
            return f"a local Ray instance ({self.num_cpus or os.cpu_count()} CPUs)"
        return f"the Ray cluster at {self.address}"

    def _connect(self):
        ray = require_ray()
        if ray.is_initialized():
            return ray
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR,
                                  "configure_logging": True}
        try:
            if self.address == "local":  # workers at normal priority, as --workers' processes (Ray's default: 15)
                with _environment({"RAY_worker_niceness": "0"}):
                    ray.init(num_cpus=self.num_cpus or os.cpu_count(), **kwargs)
            else:
                ray.init(address=self.address, **kwargs)
        except (ConnectionError, RuntimeError, ValueError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise MvtopError(f"--ray {self.address}: cannot connect to Ray ({first}); start a cluster with "
                             "`ray start --head`, or use --ray local") from None
        self._started = True
        return ray

    def run(self, fn: Callable, arglist: list[tuple]) -> Iterator[Outcome]:
        ray = self._connect()
        try:
            task = ray.remote(call_with_threads).options(
                num_cpus=self.cpus_per_job, max_retries=self.max_retries - 1, retry_exceptions=False)
            refs = {task.remote(fn, self.cpus_per_job, args): i for i, args in enumerate(arglist)}
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=len(pending), timeout=_RAY_WAIT_S)
                for ref in ready:
                    try:
                        yield Outcome(refs[ref], ray.get(ref))
                    except ray.exceptions.RayTaskError as err:  # fn raised: its own exception
                        cause = err.as_instanceof_cause()
                        yield Outcome(refs[ref], error=getattr(cause, "cause", None) or cause)
                    except ray.exceptions.RayError as err:  # the worker or node died more often than retried
                        line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                        yield Outcome(refs[ref], error=MvtopError(f"{type(err).__name__}: {line}"))
        finally:
            if self._started:
                ray.shutdown()
                self._started = False


def _check_reachable(address: str, timeout_s: float = _RAY_CONNECT_TIMEOUT_S) -> None:
    """Raise one line when a ``HOST:PORT`` (or ``ray://HOST:PORT``) Ray address accepts no TCP
    connection within ``timeout_s``; other forms (``auto``) are left to Ray."""
    match = re.fullmatch(r"(?:ray://)?\[?([^\[\]/]+?)\]?:(\d+)", address.strip())
    if match is None:
        return
    host, port = match.group(1), int(match.group(2))
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return
    except OSError as err:
        reason = "timed out" if isinstance(err, TimeoutError) else (err.strerror or type(err).__name__)
        raise MvtopError(f"--ray {address}: cannot reach a Ray cluster there ({reason} after at most "
                         f"{timeout_s:g} s); check the address and that `ray start --head` runs on that "
                         "machine, or use --ray local") from None


def require_ray():
    """The ``ray`` module, or one line saying how to install it."""
    try:
        import ray
    except ImportError:
        raise MvtopError("--ray needs Ray, the optional extra: pip install -e '.[ray]' (or pip install 'ray>=2.9')") \
            from None
    return ray


def make_engine(workers: int = 1, ray: str | None = None) -> LocalEngine | RayEngine:
    """The engine for ``--workers N`` and ``--ray ADDRESS`` (``local``: a Ray instance on this
    machine with N CPUs when N > 1)."""
    if ray is None:
        return LocalEngine(workers)
    return RayEngine(ray, num_cpus=workers if ray == "local" and workers > 1 else None)
