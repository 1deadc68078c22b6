"""Soak run behind `frodo bench --only soak`: many frames through the whole graph, faster than real time,
watching what must stay bounded.

The input is the demo bag repeated with shifted stamps (`long_bag.RepeatingPlayer`, nothing held beyond the
demo bag itself), played by `run.run_bag` at `rate` times real time. A probe in the same process records:
- each node's resident memory (VmRSS of its process, from the pid in its /diagnostics reports; Linux /proc),
  sampled every `sample_period` s against the frames played so far;
- its backlog: frames played minus images the node has taken (its /diagnostics counter), i.e. what waits
  in its queues or was dropped from them (KEEP_LAST depth 100: a queue never grows beyond that, a node
  that cannot keep up loses frames); and the size figures the nodes report (frames cached, detections, ...);
- per-frame latency: from the arrival of a frame's /camera/pose at the probe to the arrival of its
  /frodo/associations (detection + association of that frame, queueing included);
- the intervals between each node's /diagnostics reports (header stamps; contract: at least 1 Hz; gaps over
  1.25 s are counted: the 1 s period plus scheduling jitter).
`summarise` turns the samples into peak / end memory and growth per 1000 frames over the second half of the
run, latency per tenth of the run, and backlog maxima; `plot` draws them.
"""
from __future__ import annotations

import io
import json
import os
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from frodo_bringup.graph import NODES
from frodo_bringup.long_bag import RepeatingPlayer
from frodo_bringup.run import IMAGE_COUNTERS, run_bag
from frodo_bringup.session import RosSession
from frodo_common import topics

# Figures of the node reports that show a queue, a cache or a per-frame cost: recorded with every sample.
SIZE_KEYS = ('frames_cached', 'detections', 'clusters', 'objects', 'codes', 'views_held', 'dense_views_held',
             'pending_objects', 'frames_missed', 'frames_republished', 'association_ms_mean', 'refine_ms_mean',
             'evidence_ms_mean')


def rss_mb(pid: int) -> float | None:
    """Resident memory of a process in MB (VmRSS from /proc), None when it is gone or unreadable."""
    try:
        with open(f'/proc/{pid}/status') as fh:
            for line in fh:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        return None
    return None


class SoakProbe:
    """Subscribes to /diagnostics, /camera/pose and /frodo/associations and samples the nodes' memory."""

    def __init__(self, node, names: list[str]):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import PointCloud2
        self.names = names
        self.lock = threading.Lock()
        self.pose_arrival: dict[int, float] = {}       # stamp ns -> monotonic arrival
        self.output_arrival: dict[int, float] = {}     # stamp ns -> first /frodo/associations arrival
        self.report_stamps: dict[str, list[float]] = {n: [] for n in names}
        self.latest: dict[str, dict[str, str]] = {}
        self.samples: list[dict[str, Any]] = []
        self.started = time.monotonic()
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 100)
        node.create_subscription(PoseStamped, topics.POSE, self._on_pose, topics.FRAME_QOS)
        node.create_subscription(PointCloud2, topics.ASSOCIATIONS, self._on_output, topics.FRAME_QOS)

    @staticmethod
    def _stamp(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def _on_pose(self, msg) -> None:
        now = time.monotonic()
        with self.lock:
            self.pose_arrival.setdefault(self._stamp(msg), now)

    def _on_output(self, msg) -> None:
        now = time.monotonic()
        with self.lock:
            self.output_arrival.setdefault(self._stamp(msg), now)   # later ones are re-sends after merges

    def _on_diagnostics(self, msg) -> None:
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        with self.lock:
            for status in msg.status:
                if status.name in self.report_stamps:
                    self.report_stamps[status.name].append(stamp)
                    self.latest[status.name] = {kv.key: kv.value for kv in status.values}

    def sample(self) -> None:
        """One row: seconds, frames played, and per node RSS (MB), backlog (frames) and size figures."""
        with self.lock:
            frames = len(self.pose_arrival)
            latest = {n: dict(v) for n, v in self.latest.items()}
        row: dict[str, Any] = {'t_s': round(time.monotonic() - self.started, 2), 'frames': frames,
                               'rss_mb': {}, 'backlog': {}, 'sizes': {}}
        row['rss_mb']['runner'] = round(rss_mb(os.getpid()) or 0.0, 1)
        for name, values in latest.items():
            pid = values.get('pid')
            memory = rss_mb(int(pid)) if pid and pid.isdigit() else None
            if memory is not None:
                row['rss_mb'][name] = round(memory, 1)
            taken = values.get(IMAGE_COUNTERS.get(name, ''))
            if taken is not None and taken.isdigit():
                row['backlog'][name] = frames - int(taken)
            sizes = {k: float(values[k]) for k in SIZE_KEYS if _is_number(values.get(k))}
            if sizes:
                row['sizes'][name] = sizes
        self.samples.append(row)

    def latencies(self) -> tuple[np.ndarray, np.ndarray, int]:
        """(frame index of each frame with an output, its latency in ms, frames played without one)."""
        with self.lock:
            poses = sorted(self.pose_arrival.items())
            outputs = dict(self.output_arrival)
        index, latency = [], []
        for i, (stamp, arrived) in enumerate(poses):
            if stamp in outputs:
                index.append(i)
                latency.append(1e3 * (outputs[stamp] - arrived))
        return np.asarray(index, dtype=np.int64), np.asarray(latency), len(poses) - len(index)


def _is_number(text: str | None) -> bool:
    try:
        float(text)
        return True
    except (TypeError, ValueError):
        return False


def growth_per_1000_frames(frames: np.ndarray, values: np.ndarray) -> float | None:
    """Slope (per 1000 frames) of a least-squares line through the samples of the second half of the run:
    ~0 for a bounded figure, the leak rate for one that keeps growing."""
    frames, values = np.asarray(frames, dtype=np.float64), np.asarray(values, dtype=np.float64)
    keep = frames >= 0.5 * frames.max() if len(frames) else frames.astype(bool)
    if keep.sum() < 3 or np.ptp(frames[keep]) == 0:
        return None
    return float(1000.0 * np.polyfit(frames[keep], values[keep], 1)[0])


def summarise(samples: list[dict[str, Any]], index: np.ndarray, latency_ms: np.ndarray,
              report_stamps: dict[str, list[float]], parts: int = 10) -> dict[str, Any]:
    """Peak / end memory and its growth, latency per tenth of the frames, backlog and size maxima, report gaps."""
    frames = np.array([s['frames'] for s in samples], dtype=np.float64)
    names = sorted({n for s in samples for n in s['rss_mb']})
    memory = {}
    for name in names:
        rows = [(s['frames'], s['rss_mb'][name]) for s in samples if name in s['rss_mb']]
        f, v = np.array(rows).T if rows else (np.zeros(0), np.zeros(0))
        if not len(v):
            continue
        half = v[f >= 0.5 * f.max()]
        slope = growth_per_1000_frames(f, v)
        memory[name] = {'peak_mb': round(float(v.max()), 1), 'mid_mb': round(float(half[0]), 1),
                        'end_mb': round(float(v[-1]), 1),
                        'growth_mb_per_1000_frames': None if slope is None else round(slope, 2)}
    blocks = []
    if len(index):
        edges = np.linspace(0, index.max() + 1, parts + 1)
        for lo, hi in zip(edges[:-1], edges[1:]):
            part = latency_ms[(index >= lo) & (index < hi)]
            if len(part):
                blocks.append({'frames': [int(lo), int(hi)], 'outputs': int(len(part)),
                               'median_ms': round(float(np.median(part)), 1),
                               'p95_ms': round(float(np.percentile(part, 95)), 1),
                               'max_ms': round(float(part.max()), 1)})
    backlog = {}
    for name in sorted({n for s in samples for n in s['backlog']}):
        values = [s['backlog'][name] for s in samples if name in s['backlog']]
        backlog[name] = {'max': int(max(values)), 'end': int(values[-1])}
    sizes: dict[str, dict[str, Any]] = {}
    for s in samples:
        for name, figures in s['sizes'].items():
            for key, value in figures.items():
                entry = sizes.setdefault(name, {}).setdefault(key, {'max': value})
                entry['max'] = max(entry['max'], value)
                entry['end'] = value
    for name, figures in sizes.items():
        for key, entry in figures.items():
            rows = [(s['frames'], s['sizes'][name][key]) for s in samples if key in s['sizes'].get(name, {})]
            f, v = np.array(rows).T
            slope = growth_per_1000_frames(f, v)
            entry['growth_per_1000_frames'] = None if slope is None else round(slope, 2)
    gaps = {}
    for name, stamps in report_stamps.items():
        diffs = np.diff(stamps[1:]) if len(stamps) > 2 else np.zeros(0)   # the first report comes at start-up
        if len(diffs):
            gaps[name] = {'reports': len(stamps), 'mean_s': round(float(diffs.mean()), 3),
                          'p95_s': round(float(np.percentile(diffs, 95)), 3), 'max_s': round(float(diffs.max()), 3),
                          'over_1_25_s': int(np.sum(diffs > 1.25))}
    latency = {}
    if len(latency_ms):
        latency = {'median_ms': round(float(np.median(latency_ms)), 1),
                   'p95_ms': round(float(np.percentile(latency_ms, 95)), 1),
                   'max_ms': round(float(latency_ms.max()), 1),
                   'last_to_first_tenth_median': round(blocks[-1]['median_ms'] / max(blocks[0]['median_ms'], 1e-3), 2)}
    return {'frames_played': int(frames.max()) if len(frames) else 0, 'memory': memory, 'latency': latency,
            'latency_by_tenth': blocks, 'backlog_frames': backlog, 'sizes': sizes, 'diagnostics_intervals': gaps}


def plot(doc: dict[str, Any], index: np.ndarray, latency_ms: np.ndarray, path: Path, subtitle: str) -> None:
    """Three panels against frames: RSS per node, per-frame latency (with its running median), backlog."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    samples = doc['samples']
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    names = sorted({n for s in samples for n in s['rss_mb']})
    for name in names:
        rows = [(s['frames'], s['rss_mb'][name]) for s in samples if name in s['rss_mb']]
        axes[0].plot(*np.array(rows).T, label=name, lw=1)
    axes[0].set(ylabel='RSS (MB)', title=f"soak: {doc['frames']} frames at {doc['rate']}x real time\n{subtitle}")
    axes[0].legend(fontsize=7, ncol=3)
    if len(latency_ms):
        axes[1].plot(index, latency_ms, ',', color='0.6', label='per frame')
        window = max(1, len(latency_ms) // 100)
        running = np.convolve(latency_ms, np.ones(window) / window, mode='valid')
        axes[1].plot(index[window - 1:], running, 'C3', lw=1, label=f'mean of {window}')
        axes[1].set_yscale('log')
        axes[1].legend(fontsize=7)
    axes[1].set(ylabel='pose -> associations (ms)')
    for name in sorted({n for s in samples for n in s['backlog']}):
        rows = [(s['frames'], s['backlog'][name]) for s in samples if name in s['backlog']]
        axes[2].plot(*np.array(rows).T, label=name, lw=1)
    axes[2].set(xlabel='frames played', ylabel='played - taken (frames)')
    axes[2].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def soak(out: Path, frames: int = 10_000, rate: float = 4.0, bag: Path | None = None, sample_period: float = 1.0,
         timeout: float = 900.0, subtitle: str = '', log: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """Play `frames` frames of `bag` (default: the demo bag, repeated) at `rate` x real time through the whole
    graph; returns the summary (and writes OUT/soak.json and OUT/soak.png)."""
    from frodo_bringup.bench import DEMO_BAG
    bag = Path(bag or DEMO_BAG)
    out.mkdir(parents=True, exist_ok=True)
    names = [n.name for n in NODES]
    stop = threading.Event()
    run_log = io.StringIO()
    with RosSession('frodo_soak_probe') as session:
        probe = SoakProbe(session.node, names)

        def sampler() -> None:
            while not stop.wait(sample_period):
                probe.sample()
                if len(probe.samples) % 60 == 0:
                    log(f'soak: {probe.samples[-1]["frames"]} frames played, RSS {probe.samples[-1]["rss_mb"]}')
        thread = threading.Thread(target=sampler, name='soak-sampler', daemon=True)
        thread.start()
        try:
            result = run_bag(bag, out / 'run', rate=rate, output=run_log, progress=False, timeout=timeout,
                             player_factory=partial(RepeatingPlayer, frames=frames))
        finally:
            stop.set()
            thread.join(timeout=5)
        probe.sample()
        index, latency_ms, without_output = probe.latencies()
        stamps = {n: list(v) for n, v in probe.report_stamps.items()}
    (out / 'run.log').write_text(run_log.getvalue())
    doc: dict[str, Any] = {'bag': bag.name, 'frames': frames, 'rate': rate, 'sample_period_s': sample_period,
                           'exit_code': result.exit_code, 'objects': len(result.records),
                           'failures': [f.describe().splitlines()[0] for f in result.failures],
                           'wall_s': round(result.seconds, 1),
                           'playback_s': round(result.play.seconds, 1) if result.play is not None else None,
                           'frames_without_output': without_output}
    doc.update(summarise(probe.samples, index, latency_ms, stamps))
    doc['samples'] = probe.samples
    (out / 'soak.json').write_text(json.dumps(doc, indent=1) + '\n')
    plot(doc, index, latency_ms, out / 'soak.png', subtitle)
    doc['plot'] = str(out / 'soak.png')
    return {k: v for k, v in doc.items() if k != 'samples'}
