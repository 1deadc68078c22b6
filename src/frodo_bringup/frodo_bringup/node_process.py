"""Entry point of one launched node process: `python -m frodo_bringup.node_process MODULE [--ros-args ...]`.

Runs `MODULE.main()` and exits with its return code. Before that it asks Linux to send this process
SIGTERM when the launcher that started it dies (even by SIGKILL), so a killed launcher leaves no
orphan nodes behind, and, before importing MODULE, turns SIGINT / SIGTERM into the stop request that
`run_node` acts on (a Ctrl-C during the imports is kept, not swallowed by them).
"""
from __future__ import annotations

import ctypes
import importlib
import os
import signal
import sys

from frodo_common.stop_signals import install_stop_handlers

_PR_SET_PDEATHSIG = 1


def terminate_with_parent() -> None:
    """Have the kernel send SIGTERM to this process when its parent exits (Linux only; no-op elsewhere)."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def main() -> int:
    """Run the node module named by the first argument with the remaining arguments as its argv."""
    if len(sys.argv) < 2:
        print('usage: python -m frodo_bringup.node_process MODULE [--ros-args ...]', file=sys.stderr)
        return 2
    module_name = sys.argv[1]
    install_stop_handlers()
    terminate_with_parent()
    sys.argv = [module_name] + sys.argv[2:]
    code = importlib.import_module(module_name).main()
    return int(code or 0)


if __name__ == '__main__':
    sys.exit(main())
