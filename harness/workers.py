"""Worker processes that leave Ctrl-C to the parent: ``worker_pool`` is a ``ProcessPoolExecutor`` whose workers
ignore SIGINT (the terminal sends it to the whole process group), so an interrupted ``screen --workers N``,
``sensing decode --workers N`` or bootstrap stops with the parent's one message, not a traceback per worker. The
parent gets the ``KeyboardInterrupt``, cancels what is queued and shuts the pool down (a worker finishes the item
it holds, seconds at most)."""

from __future__ import annotations

import signal
import threading
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable


def _quiet(initializer: Callable[..., Any] | None, initargs: tuple[Any, ...]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops the pool
    if initializer is not None:
        initializer(*initargs)


def _nothing() -> None:
    return None


def worker_pool(
    max_workers: int,
    mp_context: Any = None,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (),
) -> ProcessPoolExecutor:
    """A ``ProcessPoolExecutor`` (``max_workers``, ``mp_context``, ``initializer(*initargs)`` in each worker) whose
    workers ignore SIGINT. The processes are started here, with SIGINT ignored in the parent for that moment, so a
    spawned worker ignores it from its first instruction (a Ctrl-C during its imports raises nothing there either).
    All ``max_workers`` are started: a spawning pool otherwise starts them one per task, later, without that."""
    pool = ProcessPoolExecutor(max_workers, mp_context=mp_context, initializer=_quiet, initargs=(initializer, initargs))
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            for _ in range(max_workers):  # one task each, none idle yet: every worker process starts now
                pool.submit(_nothing)
        finally:
            signal.signal(signal.SIGINT, previous)
    return pool
