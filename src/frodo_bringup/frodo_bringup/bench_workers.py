"""`frodo bench --only optim_workers`: objects per minute against the number of optimiser workers.

For each N the bag is reconstructed end to end (`run_bag(..., optim_workers=N)`), while a probe notes when the
first image entered the graph and when the object map (`/frodo/object_states`, merged by worker 0) last
changed. Objects per minute = objects in the final map / (last map change - first image), so graph start-up
and shutdown are not counted. The workers run as separate processes, so their speed-up is bounded by the free
CPU cores (stated with the figures: on a 2-core machine shared with other jobs, two workers compete with each
other and with the rest of the graph).
"""
from __future__ import annotations

import io
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

# Cheaper optimiser settings of `--quick` (the fused and sparse stages only).
QUICK_PARAMS = 'optim_node:\n  ros__parameters:\n    dense_enabled: false\n'


def objects_per_minute(bag: Path, out: Path, workers: Sequence[int] = (1, 2), rate: float = 1.0,
                       quick: bool = False, log: Callable[[str], None] = print) -> dict[str, Any]:
    """One `run_bag` per worker count; rows of objects, seconds and objects per minute."""
    from sensor_msgs.msg import Image, PointCloud2

    from frodo_bringup.run import run_bag
    from frodo_bringup.session import RosSession
    from frodo_common import topics
    from frodo_common.conversions import cloud_to_table
    from frodo_optim.states import OBJECT_STATES

    out.mkdir(parents=True, exist_ok=True)
    params = []
    if quick:
        params = [out / 'quick_params.yaml']
        params[0].write_text(QUICK_PARAMS)
    rows = []
    for n in workers:
        times: dict[str, float] = {}
        states: dict[int, bytes] = {}
        lock = threading.Lock()

        def on_image(_msg: Image) -> None:
            with lock:
                times.setdefault('first_image', time.monotonic())

        def on_states(msg: PointCloud2) -> None:
            table = cloud_to_table(msg)
            with lock:
                changed = False
                for row in table:
                    key, value = int(row['object_id']), row.tobytes()
                    changed |= states.get(key) != value
                    states[key] = value
                if changed:
                    times['last_change'] = time.monotonic()

        log(f'optim_workers: {n} worker(s) on {bag.name} ...')
        with RosSession(f'frodo_bench_workers_{n}') as probe:
            probe.node.create_subscription(Image, topics.IMAGE, on_image, topics.FRAME_QOS)
            probe.node.create_subscription(PointCloud2, OBJECT_STATES, on_states, topics.LATCHED_QOS)
            run_out = out / f'workers_{n}'
            output = io.StringIO()
            result = run_bag(bag, run_out, params, rate=rate, output=output, progress=False, timeout=1800,
                             optim_workers=n)
            (run_out / 'run.log').write_text(output.getvalue())
        with lock:
            span = times.get('last_change', 0.0) - times.get('first_image', 0.0)
        objects = len(result.records)
        stages = sorted(r.get('stage') or '-' for r in result.records)
        rows.append({'workers': n, 'exit_code': result.exit_code, 'objects': objects, 'stages': stages,
                     'wall_s': round(result.seconds, 1), 'first_image_to_last_map_s': round(span, 1),
                     'objects_per_minute': round(60.0 * objects / span, 2) if span > 0 and objects else None})
        log(f'optim_workers: {rows[-1]}')
    return {'bag': bag.name, 'rate': rate, 'quick': quick, 'cpu_cores': os.cpu_count(), 'rows': rows}
