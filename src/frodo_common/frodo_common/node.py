"""`FrodoNode`: the base of every FroDO node (parameters from specs, diagnostics every `diagnostics_period` (0.5 s), guarded callbacks)
and `run_node`, the `main()` shared by all node entry points.

A node never crashes the graph on bad input: callbacks wrapped with `guarded` log the error, count it,
keep it as `last_error` in diagnostics and return.

Diagnostics come from a thread of their own, not from an executor timer: a timer waits behind every
callback of its group and behind the rest of the batch of ready callbacks the executor took from one
wait (rclpy runs that batch before it looks at timers again), so under load reports came 1.5-2 s apart.
The thread starts on the node's first executor spin (so the first report also says "constructed,
subscribed") and reads the node's values concurrently with its callbacks: `diagnostic_values()`
overrides must tolerate that (a report whose values changed under it is retried).
"""
from __future__ import annotations

import atexit
import ctypes
import faulthandler
import functools
import gc
import os
import signal
import sys
import threading
import time
import traceback
from collections import Counter
from typing import Any, Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from frodo_common import topics
from frodo_common.frame_cache import FrameCache
from frodo_common.params import COMMON_PARAMS, ParamSpec
from frodo_common.stop_signals import install_stop_handlers

# Diagnostic levels as ints (the message field is a single byte).
OK, WARN, ERROR = 0, 1, 2
# Longest wait of the spin loop before the stop flag set by SIGINT / SIGTERM is seen (seconds).
STOP_POLL_S = 0.1
# Attempts at collecting a report whose node values changed while being read (RuntimeError from a dict).
DIAGNOSTICS_ATTEMPTS = 3
# Longest the ROS teardown after a stop may take (destroy_node, rclpy shutdown, joining the executor's threads) before
# the process ends itself as stopped by SIGINT (seconds); well under the launcher's 10 s between SIGINT and SIGTERM.
TEARDOWN_LIMIT_S = 5.0


# Appended to every parameter's description: what `ros2 param describe` shows next to `Read only: true`.
READ_ONLY_NOTE = 'Read once at start-up: set it with a params file or --ros-args -p, not at run time (read-only).'


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The descriptor a FroDO parameter is declared with: read-only, since every node reads its parameters once,
    in its constructor (into `self.params`), and registers no on-set callback; so `ros2 param set` is refused with
    rclpy's reason ('Trying to set a read-only parameter: NAME.') instead of reporting success for a value the
    node never reads. Overrides given at start-up (params files, `-p`, `parameter_overrides`) still apply: rclpy
    applies them when the parameter is declared. A parameter made settable at run time needs an on-set callback
    that applies it, and a descriptor without read_only."""
    return ParameterDescriptor(description=f'{spec.description} {READ_ONLY_NOTE}', read_only=True)


class FrodoNode(Node):
    """Node with declared, read-only parameters (`self.params`), counters and a periodic `/diagnostics` report.

    Subclasses pass their `ParamSpec`s, add `self.count('frames_received')`-style counters, wrap
    callbacks with `self.guarded(...)` and may override `diagnostic_values()` / `diagnostic_summary()`.
    """

    def __init__(self, node_name: str, specs: tuple[ParamSpec, ...], **kwargs):
        super().__init__(node_name, **kwargs)
        self.params: dict[str, Any] = {}
        for spec in COMMON_PARAMS + tuple(specs):
            value = self.declare_parameter(spec.name, spec.default, parameter_descriptor(spec)).value
            self.params[spec.name] = value
        self.counters: Counter[str] = Counter()
        self.last_error = ''
        self._lock = threading.Lock()
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._diag_stop = threading.Event()
        self._diag_thread: threading.Thread | None = None
        self._missed_reported: dict[str, int] = {}
        # Fires on the first spin, i.e. once the subclass constructor has finished; then cancelled.
        self._diag_start_timer = self.create_timer(0.01, self._start_diagnostics)

    # ------------------------------------------------------------ errors and counters
    def count(self, name: str, n: int = 1) -> None:
        """Increment a diagnostics counter."""
        with self._lock:
            self.counters[name] += n

    def report_error(self, where: str, err: BaseException | str, counter: str = 'errors') -> None:
        """Log an error, count it and keep it as last_error; never raises."""
        text = f'{where}: {err}'
        with self._lock:
            self.counters[counter] += 1
            self.last_error = text
        self.get_logger().error(text, throttle_duration_sec=2.0)

    def guarded(self, callback: Callable, where: str | None = None) -> Callable:
        """Wrap a callback so that an exception is reported instead of killing the node."""
        label = where or getattr(callback, '__name__', 'callback')

        @functools.wraps(callback)
        def wrapper(*args, **kwargs):
            try:
                return callback(*args, **kwargs)
            except Exception as err:  # noqa: BLE001 - a node must survive bad input
                self.get_logger().debug(traceback.format_exc())
                self.report_error(label, err)
                return None
        return wrapper

    # ------------------------------------------------------------ diagnostics
    def diagnostic_values(self) -> dict[str, Any]:
        """Node-specific key/values for the report (override)."""
        return {}

    def diagnostic_summary(self) -> tuple[int, str]:
        """(level, message) for the report (override); default WARN while errors are recent."""
        if self.last_error:
            return WARN, f'running; last error: {self.last_error}'
        return OK, 'running'

    def _start_diagnostics(self) -> None:
        self._diag_start_timer.cancel()
        if self._diag_thread is None:
            self._diag_thread = threading.Thread(target=self._diagnostics_loop, name=f'{self.get_name()}-diagnostics',
                                                 daemon=True)
            self._diag_thread.start()

    def _diagnostics_loop(self) -> None:
        """Report now, then every `diagnostics_period` seconds on a fixed schedule, until the node is destroyed."""
        period = max(float(self.params['diagnostics_period']), 0.01)
        due = time.monotonic()
        while self.context.ok():
            self.publish_diagnostics()
            due = max(due + period, time.monotonic())
            if self._diag_stop.wait(due - time.monotonic()):
                return

    def destroy_node(self) -> None:
        """Stop the diagnostics thread, then destroy the node."""
        self._diag_stop.set()
        if self._diag_thread is not None and self._diag_thread is not threading.current_thread():
            self._diag_thread.join(timeout=5.0)
        super().destroy_node()

    def frame_cache_values(self) -> dict[str, Any]:
        """What each FrameCache attribute of the node missed; warns when the count grew since the last report.

        Frames that never complete mean data this node did not get: it started after the bag (or a stream)
        began, or an upstream node or topic is silent. Reported for every node without code of its own.
        """
        values: dict[str, Any] = {}
        caches = [(attr, cache) for attr, cache in list(vars(self).items()) if isinstance(cache, FrameCache)]
        for attr, cache in caches:
            prefix = f'{attr}_' if len(caches) > 1 else ''   # keys: frames_missed, missing_parts, duplicate_parts
            count, parts = cache.missed()
            values[f'{prefix}frames_missed'] = count
            if cache.duplicates:
                values[f'{prefix}duplicate_parts'] = cache.duplicates
            if count:
                missing = ', '.join(f'{part} ({n})' for part, n in parts.most_common())
                values[f'{prefix}missing_parts'] = missing
                if count > self._missed_reported.get(attr, 0):
                    self._missed_reported[attr] = count
                    self.report_error('frame cache', f'{count} frame(s) never complete, missing {missing}: started '
                                      'after the data began, or an upstream node/topic is silent', counter='warnings')
        return values

    def _collect(self) -> tuple[int, str, dict[str, Any]]:
        """(level, message, key/values) of one report; retried when node state changed while being read."""
        for attempt in range(DIAGNOSTICS_ATTEMPTS):
            try:
                node_values = {**self.frame_cache_values(), **self.diagnostic_values()}
                level, message = self.diagnostic_summary()
                break
            except RuntimeError:  # a dict of the node resized by a callback while it was read
                if attempt == DIAGNOSTICS_ATTEMPTS - 1:
                    raise
        with self._lock:
            values = {**dict(self.counters), 'last_error': self.last_error, 'pid': os.getpid()}
        values.update(node_values)
        return level, message, values

    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticStatus for this node on /diagnostics."""
        try:
            level, message, values = self._collect()
            status = DiagnosticStatus(level=bytes([level]), name=self.get_name(), message=message,
                                      hardware_id=self.get_fully_qualified_name(),
                                      values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])
            msg = DiagnosticArray(status=[status])
            msg.header.stamp = self.get_clock().now().to_msg()
            self._diag_pub.publish(msg)
        except Exception as err:  # noqa: BLE001
            if self.context.ok():
                self.get_logger().error(f'diagnostics failed: {err}', throttle_duration_sec=5.0)


def freeze_startup_objects() -> int:
    """Move every object that exists now (modules, torch, a loaded prior: ~400k in optim_node) to the garbage
    collector's permanent generation; returns how many are frozen.

    Why: a full collection traverses every tracked object while holding the GIL. A node that allocates many
    short-lived objects (the optimiser's object map is ~40k Point messages per object) triggers full
    collections; over the startup objects each took 0.5-1 s on a loaded 2-core machine and held back the
    /diagnostics thread (reports up to 2.4 s apart). Objects built at startup live as long as the node anyway.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class _Timespec(ctypes.Structure):
    _fields_ = [('tv_sec', ctypes.c_long), ('tv_nsec', ctypes.c_long)]


class _ITimerspec(ctypes.Structure):
    _fields_ = [('it_interval', _Timespec), ('it_value', _Timespec)]


class _SigEvent(ctypes.Structure):
    """Linux `struct sigevent` (64 bytes) as far as SIGEV_SIGNAL needs it."""
    _fields_ = [('sigev_value', ctypes.c_void_p), ('sigev_signo', ctypes.c_int), ('sigev_notify', ctypes.c_int),
                ('_rest', ctypes.c_int * 12)]


def _kernel_signal_after(signum: int, seconds: float) -> Callable[[], None] | None:
    """Have the kernel send `signum` to this process after `seconds` (a POSIX timer: no thread of ours, no GIL);
    returns the function that cancels it, None where such timers are not available."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        timer = ctypes.c_void_p()
        event = _SigEvent(sigev_signo=signum, sigev_notify=0)   # SIGEV_SIGNAL
        if libc.timer_create(time.CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
            return None
        whole = int(seconds)
        expiry = _ITimerspec(it_value=_Timespec(whole, int((seconds - whole) * 1e9)))
        if libc.timer_settime(timer, 0, ctypes.byref(expiry), None) != 0:
            libc.timer_delete(timer)
            return None
        return lambda: libc.timer_delete(timer)
    except (OSError, AttributeError):
        return None


def bound_teardown(limit_s: float = TEARDOWN_LIMIT_S) -> None:
    """Make the ROS teardown of this process end within `limit_s` + 0.5 s, however it goes.

    Why: a stall inside rcl / DDS teardown runs in C with the GIL held (or in a join the stop flag cannot
    shorten), so neither the stop flag nor the launcher's SIGTERM ends it; in CI a stub node outlived SIGINT
    and SIGTERM until the launcher's SIGKILL, its subscriptions already destroyed. From here on SIGINT and
    SIGTERM have their default effect (a second Ctrl-C kills at once); after `limit_s` every thread's stack goes
    to stderr (faulthandler's watchdog needs no GIL), so the log names the stall, and 0.5 s later a kernel timer
    sends SIGINT, which ends the process the way Ctrl-C does: the status the launcher counts as a clean stop.
    Only for a process's main: nothing of it is undone (the process is ending).
    """
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_DFL)
    try:
        faulthandler.dump_traceback_later(limit_s, file=sys.stderr)
    except (ValueError, OSError, AttributeError):   # stderr without a file descriptor
        pass
    cancel = _kernel_signal_after(signal.SIGINT, limit_s + 0.5)
    # Disarmed once the threads are joined (atexit): the interpreter's finalization that follows has SIGINT and
    # SIGTERM back at their defaults anyway, so the launcher's SIGTERM ends it should it stall.
    atexit.register(faulthandler.cancel_dump_traceback_later)
    if cancel is not None:
        atexit.register(cancel)


def run_node(node_factory: Callable[[], Node], args: list[str] | None = None, threads: int = 2) -> int:
    """Init rclpy, spin the node until Ctrl-C / SIGTERM / external shutdown, then clean up; returns an exit code.

    SIGINT and SIGTERM only set a stop flag, checked between spins: a signal that arrives while the node is
    still being built (loading a prior can take seconds) stops it as soon as it is up, instead of being
    lost the way rclpy's own handlers lose it before the executor exists; one that came before (while
    `node_process` imported the node's modules) means the node is not built at all. Once the node's own
    `on_shutdown` has run, the ROS teardown is bounded (`bound_teardown`).

    threads: the executor's threads (1: every callback in this thread).
    """
    stop = install_stop_handlers()   # node_process installed them before the imports; a stop then is kept
    if stop.is_set():
        return 0
    rclpy.init(args=args if args is not None else sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = node_factory()
        freeze_startup_objects()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=STOP_POLL_S)
    except ExternalShutdownException:
        pass
    finally:
        if node is not None:
            shutdown_hook = getattr(node, 'on_shutdown', None)
            if shutdown_hook is not None:
                shutdown_hook()
        bound_teardown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        # Frozen objects are never collected, not even at exit: cycles among them (triton's IR attributes,
        # imported through torchvision -> torch._dynamo) outlive their extension's teardown, which then prints
        # ~50 'nanobind: leaked ...' lines. Unfrozen, the interpreter's final collection frees them.
        gc.unfreeze()
    return 0
