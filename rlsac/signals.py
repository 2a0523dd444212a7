"""SIGINT and SIGTERM in every command, one mechanism (issue #49).

Python's default SIGTERM kills the process where it stands: the MLflow run stayed RUNNING for good, temporary files
and scratch copies stayed behind, and the shell saw exit 143 with no message. Instead, while ``interrupt_on_signals``
is active (the CLI wraps every command in it), either signal raises ``Interrupted`` where the program is: the
with-blocks and finally-clauses unwind (``tracking.start_run`` ends the run KILLED with the signal in its ``error``
tag, ``io.atomic_path`` removes its temporary file, verify removes its scratch copy) and the CLI prints one
``error:`` line and exits 128 + the signal number (130, 143).

``StopOnSignal`` is the variant for a loop that can stop cleanly (``rlsac train``): the first signal only asks it
to stop; a second one raises as above.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Callable, Iterator

from rlsac.errors import Interrupted

SIGNALS = (signal.SIGINT, signal.SIGTERM)


def name(signum: int) -> str:
    return signal.Signals(signum).name


def raise_interrupted(signum: int, frame=None) -> None:
    """The handler: stop at once, by raising ``Interrupted`` (exit 128 + ``signum``) where the program is."""
    raise Interrupted(f"interrupted by {name(signum)}", signum)


def interrupted_in(exc: BaseException | None) -> Interrupted | None:
    """The ``Interrupted`` an exception wraps, if any (its ``__cause__`` / ``__context__`` chain). A signal's handler
    raises wherever the program is: inside the tracking store's database commit, MLflow turns it into an
    MlflowException (issue #64: a second SIGTERM printed a 50-line traceback and the run ended FAILED); the CLI and
    ``tracking.start_run`` treat such an exception as the interruption it wraps."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, Interrupted):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def install(handler: Callable) -> dict:
    """``handler`` for SIGINT and SIGTERM -> the handlers it replaced (for ``restore``); nothing outside the main
    thread, where Python cannot set handlers (a command called from a worker thread keeps the caller's)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.signal(s, handler) for s in SIGNALS}


def restore(previous: dict) -> None:
    for s, h in previous.items():
        signal.signal(s, h if h is not None else signal.SIG_DFL)


@contextlib.contextmanager
def interrupt_on_signals() -> Iterator[None]:
    """While active: SIGINT / SIGTERM raise ``Interrupted`` (see the module's docstring)."""
    previous = install(raise_interrupted)
    try:
        yield
    finally:
        restore(previous)


class StopOnSignal:
    """While active (``with``): a first SIGINT / SIGTERM sets ``signum`` (call it: ``stop()`` -> bool) instead of
    raising, so that a loop stops at its next safe point (training: the end of the episode, after saving its state).
    A second signal raises ``Interrupted`` as ``interrupt_on_signals`` does: the with-blocks unwind, so the MLflow run
    ends KILLED and a save in progress removes its temporary file (issue #28, item 5)."""

    def __init__(self, what: str = "rlsac train", safe_point: str = "the end of the episode",
                 again: str = "without saving; continue from the last saved state with --resume"):
        self.signum = 0
        self.what, self.safe_point, self.again = what, safe_point, again
        self._previous: dict = {}

    def __call__(self) -> bool:
        return bool(self.signum)

    def _handle(self, signum, frame) -> None:
        if self.signum:
            raise Interrupted(f"interrupted by a second {name(signum)}: stopped at once, {self.again}", signum)
        self.signum = signum
        print(f"\n{self.what}: {name(signum)} received, stopping at {self.safe_point} (send it again to stop at "
              "once)", file=sys.stderr, flush=True)

    def __enter__(self):
        self._previous = install(self._handle)
        return self

    def __exit__(self, *exc) -> None:
        restore(self._previous)
        self._previous = {}
