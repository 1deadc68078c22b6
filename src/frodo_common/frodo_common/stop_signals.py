"""The stop request of a node process: one event, set by SIGINT / SIGTERM from the first moment of the process.

Standard library only, so a node process can install it before importing anything heavy: a Ctrl-C that comes
while the node's modules are still being imported (torch takes seconds on a loaded machine) is otherwise a
KeyboardInterrupt that torch's import machinery swallows, or nothing at all when the process inherited SIGINT
ignored (background jobs of CI shells); either way the node came up and ran on until the launcher's SIGTERM.
"""
from __future__ import annotations

import signal
import threading

STOP_REQUESTED = threading.Event()


def install_stop_handlers() -> threading.Event:
    """From now on SIGINT and SIGTERM only set `STOP_REQUESTED` (idempotent); returns it."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: STOP_REQUESTED.set())
    return STOP_REQUESTED
