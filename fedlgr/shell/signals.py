"""SIGTERM handled like Ctrl-C (its default action skips every ``finally``, leaving an MLflow run
RUNNING): :func:`terminate_as_interrupt` raises :class:`Terminated` instead, a KeyboardInterrupt."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM inside :func:`terminate_as_interrupt`."""


# Inside ``deferred()`` an interrupt waits for the block's end: an MLflow sqlite write cut in half
# can leave this process holding the database lock that its clean-up then waits on.
_depth = 0
_pending: KeyboardInterrupt | None = None


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Ctrl-C / SIGTERM arriving inside the block (under :func:`terminate_as_interrupt`) is raised
    when the block ends; later ones are ignored."""
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


def _in_finaliser(frame, depth: int = 8) -> bool:
    """Whether the handler interrupted a finaliser (``__del__``, a weakref callback): Python prints
    an exception raised there and goes on, so the signal would be lost."""
    while frame is not None and depth > 0:
        code = frame.f_code
        if code.co_name == "__del__" or "weakref" in code.co_filename:
            return True
        frame, depth = frame.f_back, depth - 1
    return False


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`Terminated` in the main thread (elsewhere
    the block runs unchanged). Only the first signal raises, so a second (another Ctrl-C, Slurm
    signalling every process) cannot cut the clean-up short and leave a run RUNNING."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def on_signal(signum: int, frame) -> None:
        global _pending
        if _in_finaliser(frame):  # raised here, it would be printed and dropped: again, later
            timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
            timer.daemon = True
            timer.start()
            return
        if received:
            return  # the first one's interrupt is unwinding
        received.append(signum)
        name = signal.Signals(signum).name
        interrupt = KeyboardInterrupt() if signum == signal.SIGINT else Terminated(name)
        if _depth > 0 and _pending is None:
            _pending = interrupt  # raised when ``deferred()`` ends
            return
        raise interrupt

    numbers = [signal.SIGTERM, signal.SIGINT]
    # SIGHUP (a closed terminal, a dropped ssh session) as SIGTERM, unless ignored (nohup).
    if signal.getsignal(signal.SIGHUP) == signal.SIG_DFL:
        numbers.append(signal.SIGHUP)
    previous = {number: signal.signal(number, on_signal) for number in numbers}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_DFL if handler is None else handler)


def quiet_exit(code: int = 130) -> None:
    """From now on Ctrl-C or SIGTERM ends the process at once with ``code``, silently: for a process
    already exiting after an interrupt, where another would print a traceback from an ``atexit``
    hook."""

    def now(signum: int, frame) -> None:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os._exit(code)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, now)
        signal.signal(signal.SIGTERM, now)
