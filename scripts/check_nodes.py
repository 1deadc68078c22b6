"""Start every installed FroDO node executable once; each must publish /diagnostics and stop on SIGINT.

Usage: python scripts/check_nodes.py INSTALL_DIR   (a colcon install space)
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray

RRD = Path(tempfile.gettempdir()) / 'frodo_node_check.rrd'
# (package, executable, extra arguments): the viewer saves to a file instead of spawning a window.
NODES = [('frodo_detection', 'detection_node', []), ('frodo_association', 'association_node', []),
         ('frodo_shape', 'shape_node', []), ('frodo_optim', 'optim_node', []),
         ('frodo_bringup', 'viewer_node', ['--ros-args', '-p', 'mode:=save', '-p', f'rrd_path:={RRD}'])]


def main() -> int:
    install = Path(sys.argv[1] if len(sys.argv) > 1 else 'install')
    # A private ROS domain: diagnostics of nodes of another graph on this machine must not count as ours.
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(50, 100)))
    rclpy.init()
    node = rclpy.create_node('frodo_node_check')
    seen: set[tuple[str, str]] = set()   # (node name, pid) of each report: only our own process counts
    node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: seen.update(
        (s.name, next((kv.value for kv in s.values if kv.key == 'pid'), '')) for s in m.status), 50)
    failures = []
    for package, exe, extra in NODES:
        path = install / package / 'lib' / package / exe
        if not path.exists():
            failures.append(f'{exe}: executable missing at {path}')
            continue
        proc = subprocess.Popen([str(path), *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True, env=os.environ.copy())
        deadline = time.time() + 60
        while (exe, str(proc.pid)) not in seen and time.time() < deadline and proc.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.2)
        up = (exe, str(proc.pid)) in seen
        os.killpg(proc.pid, signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, _ = proc.communicate()
            failures.append(f'{exe}: did not stop within 15 s of SIGINT')
        status = 'ok' if up and proc.returncode == 0 else 'FAILED'
        print(f'{exe:18s} diagnostics={"yes" if up else "no":3s} exit={proc.returncode} {status}')
        if not up or proc.returncode != 0:
            failures.append(f'{exe}: diagnostics={up} exit={proc.returncode}\n' + '\n'.join(out.splitlines()[-15:]))
    node.destroy_node()
    rclpy.shutdown()
    frodo = install / 'frodo_bringup' / 'lib' / 'frodo_bringup' / 'frodo'
    cli = subprocess.run([str(frodo), '--help'], capture_output=True, text=True) if frodo.exists() else None
    print(f'{"frodo --help":18s} exit={cli.returncode if cli else "missing"} {"ok" if cli and cli.returncode == 0 else "FAILED"}')
    if cli is None or cli.returncode != 0:
        failures.append(f'frodo --help: {cli.stderr if cli else f"{frodo} missing"}')
    for f in failures:
        print('FAILED', f, file=sys.stderr)
    print(f'{len(NODES) + 1 - len(failures)} passed, {len(failures)} failed')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
