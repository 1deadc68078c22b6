"""`Launcher`: run graph nodes as child processes, prefix their logs, react to crashes, shut down cleanly.

Each node runs in its own process group (`python -m frodo_bringup.node_process MODULE --ros-args ...`),
so a Ctrl-C in the terminal reaches only the launcher, which then stops the nodes in order: SIGINT to
every group, SIGTERM after `sigint_timeout`, SIGKILL after `sigterm_timeout`. Children also get
SIGTERM from the kernel if the launcher itself is killed (see `node_process`). All process handling
runs on one monitor thread, which lives until the whole graph is down.
"""
from __future__ import annotations

import collections
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence, TextIO

from frodo_bringup.graph import GraphError, GraphNode, resolve_params_file, ros_parameter_arguments, shipped_presets

FAILURE_POLICIES = ('stop', 'restart', 'ignore')
TAIL_LINES = 20
_COLOURS = (36, 33, 35, 32, 34, 31)
_CLEAN_SIGINT_CODES = (0, -signal.SIGINT, 128 + signal.SIGINT)


def describe_returncode(code: int) -> str:
    """'exited with code 3' / 'was killed by SIGSEGV'."""
    if code < 0:
        try:
            return f'was killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'was killed by signal {-code}'
    return f'exited with code {code}'


@dataclass
class NodeExit:
    """A node process that ended: why, and its last log lines."""

    name: str
    returncode: int
    last_lines: list[str]
    expected: bool  # True when the launcher had asked it to stop

    @property
    def failed(self) -> bool:
        """True for a crash (any exit but 0 while running) or an unclean stop (error code or killed after SIGINT)."""
        if self.expected:
            return self.returncode not in _CLEAN_SIGINT_CODES
        return self.returncode != 0

    def describe(self) -> str:
        """Human-readable report with the last log lines."""
        text = f'{self.name} {describe_returncode(self.returncode)}'
        if self.last_lines:
            text += '; last log lines:\n' + '\n'.join(f'    {line}' for line in self.last_lines)
        return text


@dataclass
class _NodeProcess:
    node: GraphNode
    colour: int
    popen: subprocess.Popen | None = None
    reader: threading.Thread | None = None
    tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=TAIL_LINES))
    restarts: int = 0
    restart_at: float | None = None
    stopped: bool = False  # True once its exit was handled (and it is not going to restart)

    @property
    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None


class Launcher:
    """Start graph nodes as processes and keep them under a failure policy until shut down.

    >>> launcher = Launcher(NODES, params_files=[share_file('config/frodo.yaml')])
    >>> launcher.start()
    >>> launcher.wait()          # returns when the graph is down (a crash under 'stop', or shutdown())
    >>> launcher.returncode      # 0 when no node failed
    """

    def __init__(self, nodes: Sequence[GraphNode], params_files: Iterable[str | os.PathLike] = (),
                 on_failure: str = 'stop', log_dir: str | os.PathLike | None = None,
                 output: TextIO | None = None, env: dict[str, str] | None = None,
                 max_restarts: int = 3, restart_delay: float = 1.0,
                 sigint_timeout: float = 10.0, sigterm_timeout: float = 3.0,
                 on_exit: Callable[[NodeExit], None] | None = None):
        if on_failure not in FAILURE_POLICIES:
            raise GraphError(f'unknown failure policy {on_failure!r}; use one of {", ".join(FAILURE_POLICIES)}')
        if not nodes:
            raise GraphError('no nodes to launch')
        names = [n.name for n in nodes]
        if len(set(names)) != len(names):
            raise GraphError(f'node names must be unique: {", ".join(sorted({n for n in names if names.count(n) > 1}))}')
        self.params_files = [resolve_params_file(p) for p in params_files]
        for path in self.params_files:
            if not path.is_file():
                raise GraphError(f'parameter file not found: {path} (a file, or a shipped one by name: '
                                 f'{", ".join(shipped_presets())})')
        for node in nodes:   # a params file that is not YAML is refused here, not when a node is spawned
            ros_parameter_arguments(node, self.params_files)
        self.on_failure = on_failure
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.output = output if output is not None else sys.stdout
        self.env = dict(env) if env is not None else None
        self.max_restarts = max_restarts
        self.restart_delay = restart_delay
        self.sigint_timeout = sigint_timeout
        self.sigterm_timeout = sigterm_timeout
        self.on_exit = on_exit
        self.exits: list[NodeExit] = []
        self._procs = [_NodeProcess(node, _COLOURS[i % len(_COLOURS)]) for i, node in enumerate(nodes)]
        self._write_lock = threading.Lock()
        self._requests: queue.Queue[str] = queue.Queue()
        self._started = threading.Event()
        self._down = threading.Event()
        self._monitor: threading.Thread | None = None
        self._start_error: BaseException | None = None
        self._colour = self.output.isatty() if hasattr(self.output, 'isatty') else False

    # ------------------------------------------------------------------ public API
    @property
    def node_names(self) -> list[str]:
        """Names of all nodes of this launch."""
        return [p.node.name for p in self._procs]

    @property
    def pids(self) -> dict[str, int]:
        """{node name: pid} of the processes started last (alive or not)."""
        return {p.node.name: p.popen.pid for p in self._procs if p.popen is not None}

    @property
    def is_down(self) -> bool:
        """True once every node has exited and the launcher will not restart any."""
        return self._down.is_set()

    @property
    def failures(self) -> list[NodeExit]:
        """Node exits that count as failures (crashes, unclean stops)."""
        return [e for e in self.exits if e.failed]

    @property
    def returncode(self) -> int:
        """0 when no node failed, 1 otherwise."""
        return 1 if self.failures else 0

    def start(self) -> None:
        """Start every node (on the monitor thread); returns once all processes are spawned."""
        if self._monitor is not None:
            raise GraphError('launcher already started')
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        self._monitor = threading.Thread(target=self._monitor_loop, name='frodo-launcher', daemon=True)
        self._monitor.start()
        self._started.wait()
        if self._start_error is not None:
            self._down.wait()
            raise GraphError(f'could not start the graph: {self._start_error}') from self._start_error

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the graph is down (or timeout); returns True when down."""
        return self._down.wait(timeout)

    def shutdown(self, timeout: float | None = None) -> bool:
        """Stop all nodes (SIGINT, then SIGTERM, then SIGKILL) and wait; returns True when down."""
        if self._monitor is None:  # never started
            return True
        self._requests.put('stop')
        return self.wait(timeout)

    def kill(self) -> None:
        """Stop all nodes now with SIGKILL (a second Ctrl-C)."""
        self._requests.put('kill')

    def log(self, text: str) -> None:
        """Write a launcher message (prefixed `[frodo]`) to the output."""
        self._write('frodo', text, 1)

    # ------------------------------------------------------------------ processes
    def _command(self, node: GraphNode) -> list[str]:
        command = [sys.executable, '-u', '-m', 'frodo_bringup.node_process', node.module,
                   '--ros-args', '-r', f'__node:={node.name}']
        for path in self.params_files:
            command += ['--params-file', str(path)]
        return command + ros_parameter_arguments(node, self.params_files)   # after the files: they win

    def _child_env(self) -> dict[str, str]:
        env = dict(self.env if self.env is not None else os.environ)
        env['PYTHONUNBUFFERED'] = '1'
        env.setdefault('RCUTILS_COLORIZED_OUTPUT', '1' if self._colour else '0')
        if self.log_dir is not None:
            env['ROS_LOG_DIR'] = str(self.log_dir / 'ros')
        return env

    def _spawn(self, proc: _NodeProcess) -> None:
        proc.popen = subprocess.Popen(self._command(proc.node), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, env=self._child_env() | dict(proc.node.env),
                                      start_new_session=True)
        proc.restart_at = None
        proc.stopped = False
        log_file = self.log_dir / f'{proc.node.name}.log' if self.log_dir is not None else None
        proc.reader = threading.Thread(target=self._pump_output, args=(proc, proc.popen, log_file),
                                       name=f'frodo-log-{proc.node.name}', daemon=True)
        proc.reader.start()
        self.log(f'started {proc.node.name} (pid {proc.popen.pid})')

    def _pump_output(self, proc: _NodeProcess, popen: subprocess.Popen, log_file: Path | None) -> None:
        sink = open(log_file, 'a', encoding='utf-8') if log_file is not None else None
        try:
            for raw in popen.stdout:
                line = raw.decode('utf-8', errors='replace').rstrip('\r\n')
                proc.tail.append(line)
                self._write(proc.node.name, line, proc.colour)
                if sink is not None:
                    sink.write(line + '\n')
                    sink.flush()
        finally:
            popen.stdout.close()
            if sink is not None:
                sink.close()

    def _write(self, name: str, line: str, colour: int) -> None:
        prefix = f'\033[{colour}m[{name}]\033[0m' if self._colour else f'[{name}]'
        with self._write_lock:
            try:
                self.output.write(f'{prefix} {line}\n')
                self.output.flush()
            except (ValueError, OSError):  # output closed while shutting down
                pass

    @staticmethod
    def _signal_group(popen: subprocess.Popen, sig: int) -> None:
        try:
            os.killpg(popen.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    # ------------------------------------------------------------------ monitor thread
    def _monitor_loop(self) -> None:
        try:
            for proc in self._procs:
                self._spawn(proc)
        except OSError as err:
            self._start_error = err
            self._requests.put('stop')
        self._started.set()
        stop_started: float | None = None
        escalation = 0  # 0: SIGINT sent, 1: SIGTERM sent, 2: SIGKILL sent
        while True:
            request = self._next_request()
            if request == 'stop' and stop_started is None:
                stop_started = self._begin_stop()
            elif request == 'kill':
                stop_started = stop_started or time.monotonic()
                escalation = self._escalate(2)
            self._handle_exits(expected=stop_started is not None)
            if stop_started is None:
                self._restart_due()
                if self._stop_needed():
                    stop_started = self._begin_stop()
            else:
                escalation = self._escalate_if_late(stop_started, escalation)
            if all(not p.alive for p in self._procs) and (stop_started is not None or self._none_pending()):
                self._handle_exits(expected=stop_started is not None)
                break
        for proc in self._procs:  # leftovers of a process group (children of a node)
            if proc.popen is not None:
                self._signal_group(proc.popen, signal.SIGKILL)
        self._down.set()

    def _next_request(self) -> str | None:
        try:
            return self._requests.get(timeout=0.1)
        except queue.Empty:
            return None

    def _begin_stop(self) -> float:
        alive = [p for p in self._procs if p.alive]
        if alive:
            self.log(f'stopping {", ".join(p.node.name for p in alive)}')
        for proc in alive:
            self._signal_group(proc.popen, signal.SIGINT)
        for proc in self._procs:
            if proc.restart_at is not None:  # dead, waiting for a restart that is now cancelled
                proc.restart_at = None
                proc.stopped = True
        return time.monotonic()

    def _escalate_if_late(self, stop_started: float, escalation: int) -> int:
        elapsed = time.monotonic() - stop_started
        if escalation == 0 and elapsed > self.sigint_timeout:
            return self._escalate(1)
        if escalation == 1 and elapsed > self.sigint_timeout + self.sigterm_timeout:
            return self._escalate(2)
        return escalation

    def _escalate(self, level: int) -> int:
        sig = signal.SIGTERM if level == 1 else signal.SIGKILL
        for proc in self._procs:
            if proc.alive:
                self.log(f'{proc.node.name} did not stop, sending {sig.name}')
                self._signal_group(proc.popen, sig)
        return level

    def _handle_exits(self, expected: bool) -> None:
        for proc in self._procs:
            if proc.popen is None or proc.stopped or proc.restart_at is not None or proc.alive:
                continue
            if proc.reader is not None:
                proc.reader.join(timeout=1.0)
            record = NodeExit(proc.node.name, proc.popen.returncode, list(proc.tail), expected)
            self.exits.append(record)
            proc.stopped = True
            if record.failed or not expected:
                self.log(record.describe() if record.failed else f'{proc.node.name} exited')
            if not expected:
                self._apply_policy(proc)
            if self.on_exit is not None:
                self.on_exit(record)

    def _apply_policy(self, proc: _NodeProcess) -> None:
        if self.on_failure == 'restart':
            if proc.restarts < self.max_restarts:
                proc.restarts += 1
                proc.restart_at = time.monotonic() + self.restart_delay
                proc.stopped = False
                self.log(f'restarting {proc.node.name} in {self.restart_delay:.0f} s '
                         f'(restart {proc.restarts} of {self.max_restarts})')
            else:
                self.log(f'{proc.node.name} failed {proc.restarts + 1} times, stopping the graph')
        elif self.on_failure == 'stop':
            self.log(f'{proc.node.name} is down, stopping the graph (--on-failure stop)')

    def _restart_due(self) -> None:
        now = time.monotonic()
        for proc in self._procs:
            if proc.restart_at is not None and now >= proc.restart_at:
                proc.tail.clear()
                self._spawn(proc)

    def _stop_needed(self) -> bool:
        """Under 'stop' any unexpected exit stops the graph; under 'restart' one that used up its restarts."""
        if self.on_failure == 'ignore':
            return False
        return any(p.stopped for p in self._procs)

    def _none_pending(self) -> bool:
        return all(p.restart_at is None for p in self._procs)
