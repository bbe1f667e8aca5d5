"""Where many independent tasks run: a local process pool, or a Ray cluster. One interface for both.

    with make_backend("local", workers=2) as backend:
        for index, result in backend.map(fn, tasks):
            ...

`map` runs a picklable module-level function on every task and yields (task index, result) as results
come, in whatever order they finish. The local backend is a pool of spawned processes (each keeps its
module-level caches between tasks); the Ray backend sends the tasks to the cluster at `RAY_ADDRESS`
(or a local Ray when unset, with `workers` CPUs), keeping a few tasks per CPU in flight so a sweep of
millions holds no more than that in Ray's object store. `vrscroll sweep`, `evaluate` and `tune` take
`--backend`. Ray is an optional extra (`pip install -e '.[ray]'`), imported only when chosen.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator

BACKENDS = ("local", "ray")
IN_FLIGHT_PER_CPU = 4  # Ray: tasks submitted ahead per cluster CPU
# --workers per core of this machine at most: a task keeps a core busy, so a worker beyond the cores only waits,
# holding its ~0.9 GB (MuJoCo, the target's fields, its twins); four a core leaves room to oversubscribe on
# purpose, and `--workers 5000` (some 4.5 TB) is refused before a process starts
WORKERS_PER_CORE = 4


def _indexed(fn: Callable, item: tuple):
    index, task = item
    return index, fn(task)


class LocalBackend:
    """A pool of `workers` spawned processes, started on the first map and kept until close."""

    name = "local"

    def __init__(self, workers: int | None = None):
        self.workers = workers or os.cpu_count() or 1
        self._pool = None

    def map(self, fn: Callable, tasks: Iterable) -> Iterator[tuple[int, object]]:
        if self._pool is None:
            self._pool = multiprocessing.get_context("spawn").Pool(self.workers)
        yield from self._pool.imap_unordered(functools.partial(_indexed, fn), enumerate(tasks), chunksize=1)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class RayBackend:
    """Tasks on Ray: the cluster at RAY_ADDRESS, the Ray this process already joined, or a local one."""

    name = "ray"

    def __init__(self, workers: int | None = None):
        try:
            import ray
        except ImportError:
            raise ValueError("the ray backend needs Ray: pip install -e '.[ray]' (or pip install 'ray>=2.9')") from None
        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            address = os.environ.get("RAY_ADDRESS")
            ray.init(address=address or None, num_cpus=None if address else (workers or os.cpu_count()),
                     include_dashboard=False, log_to_driver=False)
        self.workers = int(ray.cluster_resources().get("CPU", 1))

    def map(self, fn: Callable, tasks: Iterable) -> Iterator[tuple[int, object]]:
        ray = self._ray
        remote = ray.remote(num_cpus=1)(_indexed)
        fn_ref = ray.put(fn)
        todo = iter(enumerate(tasks))
        pending = []
        window = IN_FLIGHT_PER_CPU * self.workers
        while True:
            for item in todo:
                pending.append(remote.remote(fn_ref, item))
                if len(pending) >= window:
                    break
            if not pending:
                return
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])

    def close(self) -> None:
        if self._started and self._ray.is_initialized():
            self._ray.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def make_backend(name: str, workers: int | None = None):
    """A backend by name ('local' or 'ray'); workers: local processes, or a local Ray's CPUs (default all cores);
    ValueError for workers below 1 or over WORKERS_PER_CORE a core."""
    cores = os.cpu_count() or 1
    if workers is not None and not 1 <= workers <= WORKERS_PER_CORE * cores:
        raise ValueError(f"--workers {workers}: from 1 to {WORKERS_PER_CORE * cores} ({WORKERS_PER_CORE} per core, "
                         f"WORKERS_PER_CORE; this machine has {cores})")
    if name == "local":
        return LocalBackend(workers)
    if name == "ray":
        return RayBackend(workers)
    raise ValueError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")


def add_backend_arguments(p, workers_default: int | None = None) -> None:
    """--backend and --workers for a command that farms out tasks."""
    p.add_argument("--backend", choices=BACKENDS, default="local",
                   help="where tasks run: local worker processes, or Ray (RAY_ADDRESS, or a local Ray when unset; "
                        "needs the ray extra) (default %(default)s)")
    p.add_argument("--workers", type=int, default=workers_default,
                   help=f"worker processes, or a local Ray's CPUs, at most {WORKERS_PER_CORE} per core (default " +
                        (f"{workers_default})" if workers_default else "all cores)"))
