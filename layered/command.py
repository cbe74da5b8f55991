"""The `layered` command: it loads the command line and then what the command runs on (torch and the
environments take seconds) with Ctrl-C held, so that Ctrl-C while it starts stops with one line, as at
any later moment; `--help` and usage errors answer before anything heavy is loaded."""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

EXIT_SIGINT = 130


@contextmanager
def sigint_held() -> Iterator[list[int]]:
    """Within the block a first SIGINT is noted in the yielded list instead of raised, and a second raises
    KeyboardInterrupt. Raised while modules load, a KeyboardInterrupt can be swallowed by a library's own
    handler (a bare `except`, a finaliser) or leave a module half loaded, and the command then runs on."""
    received: list[int] = []

    def note(signum: int, frame: FrameType | None) -> None:
        if received:
            raise KeyboardInterrupt
        received.append(signum)

    before = signal.signal(signal.SIGINT, note)
    try:
        yield received
    finally:
        signal.signal(signal.SIGINT, before)


def main() -> int:
    """Load and parse the command line, then run it; Ctrl-C until it runs is one line and exit code 130."""
    try:
        with sigint_held() as received:
            from layered.cli import load, parse, run

            args = parse(sys.argv[1:])
            load(args)
    except KeyboardInterrupt:
        received = [signal.SIGINT]
    if received:
        print("\nlayered: stopped while starting; nothing was written", file=sys.stderr)
        return EXIT_SIGINT
    return run(args)
