"""The ``usdeform`` console script and ``python -m usdeform``.

Ctrl-C is "usdeform: interrupted" (exit status 130) at any moment after the package's first line: this module
imports nothing heavy, and the command line (whose modules import NumPy) is imported inside the handler.
"""

from __future__ import annotations

import signal
import sys

__all__ = ["main"]


def main() -> int:
    """Run :func:`usdeform.cli.main` on ``sys.argv``; returns its exit status (130 after Ctrl-C)."""
    try:
        try:
            from .cli import main as run

            return run()
        except KeyboardInterrupt:
            print("usdeform: interrupted", file=sys.stderr)
            return 130
    finally:  # the command is over: Ctrl-C while Python shuts down (threads joined, files closed) changes nothing
        signal.signal(signal.SIGINT, signal.SIG_IGN)


if __name__ == "__main__":
    sys.exit(main())
