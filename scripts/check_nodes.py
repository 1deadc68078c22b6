"""Start every installed FroDO node executable once; each must publish /diagnostics and stop on SIGINT.

Usage: python scripts/check_nodes.py INSTALL_DIR   (a colcon install space)
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray

NODES = [('frodo_detection', 'detection_node'), ('frodo_association', 'association_node'),
         ('frodo_shape', 'shape_node'), ('frodo_optim', 'optim_node')]


def main() -> int:
    install = Path(sys.argv[1] if len(sys.argv) > 1 else 'install')
    rclpy.init()
    node = rclpy.create_node('frodo_node_check')
    seen: set[str] = set()
    node.create_subscription(DiagnosticArray, '/diagnostics',
                             lambda m: seen.update(s.name for s in m.status), 50)
    failures = []
    for package, exe in NODES:
        path = install / package / 'lib' / package / exe
        if not path.exists():
            failures.append(f'{exe}: executable missing at {path}')
            continue
        proc = subprocess.Popen([str(path)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True, env=os.environ.copy())
        deadline = time.time() + 60
        while exe not in seen and time.time() < deadline and proc.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.2)
        up = exe in seen
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
    for f in failures:
        print('FAILED', f, file=sys.stderr)
    print(f'{len(NODES) - len(failures)} passed, {len(failures)} failed')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
