"""Stopping cleanly on Ctrl-C (SIGINT) and SIGTERM: one signal stops everything within seconds, leaves no process
behind and nothing half-written.

* :func:`stop_signals_raise` (used by the CLI around every command) turns SIGTERM into :class:`Terminated`, a
  :class:`KeyboardInterrupt` subclass, and SIGINT into :class:`KeyboardInterrupt`, once: repeats are ignored while
  the clean-up runs, so the same ``except`` / ``finally`` blocks that clean up after Ctrl-C
  (temporary ``.part`` files, staging folders, worker pools, the bridge's clean stop) also run when a service
  manager or ``kill`` stops the program. The CLI exits 130 after SIGINT and 143 after SIGTERM (128 + signal number,
  as a shell reports a process killed by the signal).
* :func:`worker_init` is the initializer of worker processes (the Monte Carlo process pool): a worker ignores SIGINT
  (the terminal sends Ctrl-C to the whole process group; the parent alone decides and stops the workers, so no
  worker prints a traceback), dies at once on SIGTERM, and is sent SIGTERM by the kernel when its parent dies
  (Linux ``PR_SET_PDEATHSIG``), so even a parent killed by SIGKILL leaves no orphan running under PID 1.
* :func:`deferred` holds SIGINT and SIGTERM for the few microseconds of a group of renames (a set of outputs moved
  into place), so a signal lands before or after the group, never in the middle.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

#: exit status after SIGINT / SIGTERM (128 + signal number)
EXIT_SIGINT = 128 + signal.SIGINT
EXIT_SIGTERM = 128 + signal.SIGTERM

#: ``prctl`` option number of ``PR_SET_PDEATHSIG`` (linux/prctl.h)
_PR_SET_PDEATHSIG = 1


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM (see :func:`stop_signals_raise`)."""


def _on_stop_signal(signum: int, frame: object) -> None:
    ignore_further_signals()
    if signum == signal.SIGTERM:
        raise Terminated(f"signal {signum}")
    raise KeyboardInterrupt


@contextlib.contextmanager
def stop_signals_raise() -> Iterator[None]:
    """While inside, the first SIGTERM raises :class:`Terminated` and the first SIGINT :class:`KeyboardInterrupt` in
    the main thread; repeats are then ignored, so a second Ctrl-C cannot interrupt the (bounded) clean-up half-way.
    A SIGINT that was ignored on entry (a background job) stays ignored. Handlers are restored on exit; a no-op
    outside the main thread, where signal handlers cannot be set."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGTERM, _on_stop_signal)
    if previous[signal.SIGINT] is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_stop_signal)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def ignore_further_signals() -> None:
    """Ignore SIGINT and SIGTERM from now on (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Block SIGINT and SIGTERM for the duration (POSIX); a signal that arrives meanwhile is delivered on exit."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _die_with_parent() -> None:
    """Ask the kernel to send SIGTERM to this process when its parent dies (Linux only; elsewhere nothing)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - a libc without prctl
        pass


def worker_init(parent_pid: int | None = None) -> None:
    """Initializer of a worker process (see the module docstring). ``parent_pid``: the pid that started the pool;
    if it is already gone when the worker starts (the parent died between fork and here), the worker exits."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent()
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(1)
