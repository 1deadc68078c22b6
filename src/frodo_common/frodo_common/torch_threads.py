"""Keep a node process from holding more OpenMP teams (torch's helper threads) than it needs.

Why: torch's CPU kernels run in OpenMP (libgomp) parallel regions, and every thread that enters one keeps a
team of helper threads for as long as it lives. libgomp counts the helpers of all teams, and once there are
more of them than CPUs it stops spin-waiting between regions: each helper then sleeps on a futex and is woken
for every region. A node that loaded its prior in the main thread (one team) and then optimised in a worker
thread (a second team) ran the optimiser's stages 1.5x slower on a 2-core machine than the same calls in a
process with one team (the demo walk's first dense stage: 9.0 s against 5.8 s, measured by replaying its
inputs; docs/experiments/frodo_optim_history.md, "One OpenMP team per process").

So a node loads its models in a thread that ends when they are loaded (its team ends with it:
`call_in_passing_thread`), and the optimiser node runs torch in its worker thread only (its frame callbacks cut
view crops in numpy). The rest of a node's constructor stays in the main thread (signal handlers can only be
set there). Nodes whose executor callbacks run torch (shape_node's encoder, detection_node's Mask R-CNN) keep
two executor threads: shape_node with one delayed the codes of objects confirmed while frames kept coming by
2.8-5.4 s in the live demo run (docs/experiments/frodo_optim_history.md).
"""
from __future__ import annotations

import threading
from typing import Callable, TypeVar

T = TypeVar('T')


def call_in_passing_thread(fn: Callable[[], T], name: str = 'frodo-build') -> T:
    """fn() run in a new thread that ends when it returns; its result, or its exception raised here.

    The OpenMP team that torch work in fn starts (loading weights copies tensors in parallel) ends with the
    thread, so it does not slow the thread that runs torch later (see the module docstring)."""
    outcome: dict[str, object] = {}

    def target() -> None:
        try:
            outcome['value'] = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised in the caller's thread
            outcome['error'] = err

    thread = threading.Thread(target=target, name=name)
    thread.start()
    thread.join()
    if 'error' in outcome:
        raise outcome['error']
    return outcome['value']
