"""SIGTERM handled like Ctrl-C.

``timeout``, Slurm (at the end of a job's time limit) and ``docker stop`` stop a process
with SIGTERM, whose default action ends it at once: no ``finally`` or ``except`` runs, so
an MLflow run stays RUNNING and a sweep's trial waits for its heartbeat to go stale. Inside
:func:`terminate_as_interrupt`, SIGTERM raises :class:`Terminated` - a
``KeyboardInterrupt`` - in the main thread instead, so the code that handles Ctrl-C (runs
ended KILLED, a sweep's trial queued again) handles it too.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM inside :func:`terminate_as_interrupt`."""


# Inside ``deferred()`` an interrupt waits for the block's end: a store write cut in half
# (a KeyboardInterrupt raised inside an MLflow sqlite call) can leave this process's own
# connection holding the database lock, and the clean-up's writes then wait on it in vain.
_depth = 0
_pending: KeyboardInterrupt | None = None


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Ctrl-C / SIGTERM arriving inside the block (under :func:`terminate_as_interrupt`)
    is raised when the block ends (later ones are ignored: the first one stops the
    process)."""
    global _depth, _pending
    if threading.current_thread() is not threading.main_thread():
        yield  # signals reach the main thread only
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _pending is not None:
            interrupt, _pending = _pending, None
            raise interrupt


def _raise_or_defer(interrupt: KeyboardInterrupt) -> None:
    global _pending
    if _depth > 0 and _pending is None:
        _pending = interrupt
        return
    raise interrupt


def _in_finaliser(frame, depth: int = 8) -> bool:
    """Whether the handler interrupted a finaliser (``__del__``, a weakref callback run
    by the garbage collector): Python prints an exception raised there ("Exception
    ignored in ...") and goes on, so the signal would be lost (a sweep went on for
    minutes after SIGTERM)."""
    while frame is not None and depth > 0:
        code = frame.f_code
        if code.co_name == "__del__" or "weakref" in code.co_filename:
            return True
        frame, depth = frame.f_back, depth - 1
    return False


def _again(signum: int) -> None:
    """Deliver ``signum`` to this process again in a moment, outside the finaliser."""
    timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread.

    Only the first Ctrl-C, SIGTERM or SIGHUP raises; later ones are ignored while its
    interrupt unwinds, so a second signal (an impatient second Ctrl-C, Slurm signalling
    every process of a job, a sweep forwarding SIGTERM to its worker processes) cannot cut
    the clean-up short - a run's failure record would stop before its MLflow run is ended
    and leave it RUNNING. SIGKILL still ends the process at once. Both wait for the end of
    a :func:`deferred` block. The previous handlers are restored on leaving. Outside the
    main thread (Python runs signal handlers only there) the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def on_signal(signum: int, frame) -> None:
        if _in_finaliser(frame):
            _again(signum)  # raised here, it would be printed and dropped
            return
        if received:
            return  # the first one's interrupt is unwinding
        received.append(signum)
        name = signal.Signals(signum).name
        _raise_or_defer(KeyboardInterrupt() if signum == signal.SIGINT else Terminated(name))

    previous = signal.signal(signal.SIGTERM, on_signal)
    previous_int = signal.signal(signal.SIGINT, on_signal)
    # SIGHUP (the terminal closed, an ssh session dropped) as SIGTERM, unless it is ignored
    # (nohup): its default action kills the process at once and leaves the run RUNNING.
    hangup = signal.getsignal(signal.SIGHUP) == signal.SIG_DFL
    previous_hup = signal.signal(signal.SIGHUP, on_signal) if hangup else None
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
        signal.signal(signal.SIGINT, previous_int if previous_int is not None else signal.SIG_DFL)
        if hangup:
            signal.signal(signal.SIGHUP, previous_hup or signal.SIG_DFL)


def quiet_exit(code: int = 130) -> None:
    """From now on Ctrl-C or SIGTERM ends the process at once with ``code``, silently: for a
    process that is already exiting after an interrupt. Otherwise a second Ctrl-C (or one
    redelivered by :func:`_again`) lands in an ``atexit`` hook (torch's, MLflow's), and
    Python prints its ``KeyboardInterrupt`` traceback after fedlgr's last line."""

    def now(signum: int, frame) -> None:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os._exit(code)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, now)
        signal.signal(signal.SIGTERM, now)
