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
import signal
import threading
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM inside :func:`terminate_as_interrupt`."""


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread.

    Only the first SIGTERM raises; later ones are ignored while the interrupt unwinds, so
    a second signal (Slurm signals every process of a job, and a sweep forwards SIGTERM to
    its worker processes) cannot cut the clean-up short - SIGKILL still ends the process.
    The previous handler is restored on leaving. Outside the main thread (Python runs
    signal handlers only there) the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def handler(signum: int, frame) -> None:
        if not received:
            received.append(signum)
            raise Terminated(signal.Signals(signum).name)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
