"""Process plumbing shared by the `frodo` commands: a helper node in its own rclpy context spun on a
background thread, and Ctrl-C / SIGTERM handling that turns signals into a stop event."""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Callable, Iterator

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions


class RosSession:
    """One node (`name`) in a private rclpy context; callbacks run on a background thread until `close()`."""

    def __init__(self, name: str):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f'{name}-spin', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - the context was shut down while waiting
                if self.context.ok():
                    raise
                return

    def close(self) -> None:
        """Stop spinning, destroy the node and shut the context down."""
        self.context.try_shutdown()
        self._thread.join(timeout=2.0)
        self.executor.shutdown()
        self.node.destroy_node()

    def __enter__(self) -> 'RosSession':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def stop_on_signals(on_repeat: Callable[[], None] | None = None) -> Iterator[threading.Event]:
    """Yield an event set by the first SIGINT / SIGTERM; a second one calls `on_repeat` (e.g. kill now).

    Only installs handlers when called from the main thread (elsewhere the event is just returned).
    """
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handle(signum, _frame) -> None:
        if stop.is_set() and on_repeat is not None:
            on_repeat()
        stop.set()

    previous = {sig: signal.signal(sig, handle) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
