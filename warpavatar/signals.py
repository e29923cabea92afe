"""Stop signals as interruptions: SIGINT (Ctrl-C), SIGTERM (a scheduler's or container's stop) and SIGHUP (a
logout) end a command alike, and a long job (a fit) can stop at its next safe point and write its checkpoint.

Used by the command-line tools and by the batch runner's workers; it imports nothing of the package.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator

__all__ = ["STOP_SIGNALS", "Interrupted", "interruption_signal", "interruption_exit_status",
           "termination_interrupts", "StopRequest", "stop_on_signals"]


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""The signals that end a command as Ctrl-C does: Ctrl-C itself, a scheduler's or container's stop, a logout."""


class Interrupted(KeyboardInterrupt):
    """A stop signal turned into an interruption: it unwinds like Ctrl-C's KeyboardInterrupt (``finally`` blocks
    remove temporary files) and says which signal it was.

    Attributes:
        signal_number: the signal (``signal.SIGTERM``, ``signal.SIGHUP``, ...).
    """

    def __init__(self, signal_number: int):
        super().__init__(signal.Signals(signal_number).name)
        self.signal_number = int(signal_number)


def interruption_signal(interruption: KeyboardInterrupt) -> int:
    """The signal behind ``interruption``: its :attr:`Interrupted.signal_number`, SIGINT for a plain
    KeyboardInterrupt."""
    return getattr(interruption, "signal_number", int(signal.SIGINT))


def interruption_exit_status(signal_number: int) -> int:
    """The exit status of a command ended by ``signal_number``: 128 + the number, as shells report (130 for
    SIGINT, 143 for SIGTERM, 129 for SIGHUP)."""
    return 128 + int(signal_number)


@contextlib.contextmanager
def termination_interrupts():
    """While active on the main thread, SIGTERM and SIGHUP raise :class:`Interrupted` where the program is, as
    Ctrl-C raises KeyboardInterrupt; the handlers before are restored on exit. A signal the process was started
    ignoring (``nohup``) stays ignored; elsewhere than the main thread it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signal_number, frame):
        raise Interrupted(signal_number)

    previous = {}
    for number in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(number) is not signal.SIG_IGN:
            previous[number] = signal.signal(number, interrupt)
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_DFL if handler is None else handler)


class StopRequest:
    """What :func:`stop_on_signals` yields: the signal that asked to stop (None until one came)."""

    def __init__(self):
        self.signal_number: int | None = None

    def __bool__(self) -> bool:
        return self.signal_number is not None


@contextlib.contextmanager
def stop_on_signals(request_stop: Callable[[], None] | None = None, *, even_ignored: bool = False
                    ) -> Iterator[StopRequest]:
    """While active on the main thread, the first of :data:`STOP_SIGNALS` is recorded in the yielded
    :class:`StopRequest` and calls ``request_stop`` (which must only set a flag: it runs in a signal handler), so
    that a long job stops at its next safe point; a second one raises :class:`Interrupted` at once. A signal the
    process ignores stays ignored (``nohup``) unless ``even_ignored`` (a Ray worker ignores SIGINT, which
    ``ray.cancel`` delivers). The handlers before are restored on exit; elsewhere than the main thread it does
    nothing."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def interrupt(signal_number, frame):
        raise Interrupted(signal_number)

    def handle(signal_number, frame):
        stop.signal_number = signal_number
        if request_stop is not None:
            request_stop()
        for number in previous:
            signal.signal(number, interrupt)

    previous = {number: signal.getsignal(number) for number in STOP_SIGNALS
                if even_ignored or signal.getsignal(number) is not signal.SIG_IGN}
    for number in previous:
        signal.signal(number, handle)
    try:
        yield stop
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_DFL if handler is None else handler)
