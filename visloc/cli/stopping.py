"""How a command stops on a signal: SIGTERM (``kill``) as on Ctrl-C, committing what finished, with one
line saying what stopped it and the shell's exit status (128 + the signal's number)."""

from __future__ import annotations

import signal


class Terminated(KeyboardInterrupt):
    """SIGTERM (or another stop signal) arrived: stop as on Ctrl-C, committing what finished."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def stop_on_signal(signum: int, frame: object) -> None:
    raise Terminated(signum)


def interrupted_text(exc: KeyboardInterrupt) -> str:
    return (f"stopped by {signal.Signals(exc.signum).name}" if isinstance(exc, Terminated) else "interrupted")


def interrupted_status(exc: KeyboardInterrupt) -> int:
    """The exit status of a command stopped by ``exc``: 128 + the signal's number, as the shell reports it."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else signal.SIGINT)
