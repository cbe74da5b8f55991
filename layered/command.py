"""The `layered` command: it loads the command line (torch and the environments take seconds) only once
it runs, so that Ctrl-C while it starts stops with one line, as at any later moment."""

from __future__ import annotations

import sys

EXIT_SIGINT = 130


def main() -> int:
    """Load the command line and run it; Ctrl-C while loading is one line and exit code 130."""
    try:
        from layered.cli import main as run
    except KeyboardInterrupt:
        print("\nlayered: stopped while starting; nothing was written", file=sys.stderr)
        return EXIT_SIGINT
    return run()
