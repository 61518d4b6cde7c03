"""The worker processes that render (bpy is not thread-safe): started in batches and replaced (bpy leaks
memory), and never outliving the run that started them."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

_THREADS = 0  # Cycles threads per worker (0: every core)
_DEVICE = "CPU"  # where Cycles renders a sample's views: "CPU" or "GPU"
_PARENT_PID: int | None = None

_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def cycles_threads() -> int:
    """Cycles threads for this worker, as the run chose them."""
    return _THREADS


def cycles_device() -> str:
    """Where this worker's Cycles renders the views, as the run chose it."""
    return _DEVICE


def init_worker(threads: int, parent_pid: int | None = None, device: str = "CPU") -> None:
    """Set up a fresh worker: die with the parent, quiet stdout, ``bpy`` imported once."""
    global _THREADS, _PARENT_PID, _DEVICE
    _THREADS, _DEVICE = threads, device
    _PARENT_PID = os.getppid() if parent_pid is None else parent_pid
    _die_with_parent()
    # Blender prints a line per render ("Saved: ...") on stdout: keep the parent's progress bar clean.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
    # A parent that imported bpy has Blender's script folders (holding a pure-Python ``bpy`` package)
    # on sys.path, and spawn copies that path; drop them so the real module is found.
    sys.path[:] = [p for p in sys.path if f"{os.sep}bpy{os.sep}" not in p]
    import bpy  # noqa: F401  (pay the import once per worker)


def _die_with_parent() -> None:
    """Ask Linux to SIGKILL this worker when the run dies (kill -9 included): an orphan would hold ~800 MB
    and keep writing into a folder that another run may own by then. Elsewhere only
    :func:`exit_if_orphaned` guards."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    exit_if_orphaned()  # the parent may have died before the request above


def exit_if_orphaned() -> None:
    """End this worker at once if the run that started it is gone (call before writing results)."""
    if _PARENT_PID is not None and os.getppid() != _PARENT_PID:
        os._exit(1)


def completed(tasks, workers: int, threads: int, recycle: int, device: str = "CPU"):
    """Results of ``tasks`` [(fn, args)] as they finish; a failed task stops the run with its error.
    ``device``: where the workers' Cycles renders the views (:func:`cycles_device`).

    Workers are recycled (bpy leaks memory) by running the tasks in batches, each in a fresh pool. The
    pool's own ``max_tasks_per_child`` deadlocks on Python 3.11 when a worker retires, so it is not used.
    """
    ctx = mp.get_context("spawn")
    batch = max(1, workers) * max(1, recycle)
    for start in range(0, len(tasks), batch):
        with ProcessPoolExecutor(max(1, workers), mp_context=ctx, initializer=init_worker,
                                 initargs=(threads, os.getpid(), device)) as pool:
            futures = [pool.submit(fn, *a) for fn, a in tasks[start:start + batch]]
            try:
                yield from _results(futures)
            finally:
                for f in futures:
                    f.cancel()


def _results(futures):
    for fut in as_completed(futures):
        try:
            yield fut.result()
        except BrokenProcessPool as e:
            raise RuntimeError("a datagen worker process died (crash or out of memory); rerun the "
                               "same command to resume, finished samples are kept") from e
