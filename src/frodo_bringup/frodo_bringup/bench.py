"""Benchmarks behind `frodo bench`: one JSON document (and plots) with the figures the READMEs quote.

Sections (each a function returning plain data; a section that cannot run says why instead):
- `machine`: CPU, cores, load average, torch threads, device, versions, git commit.
- `decoder`: shape prior decoders (paper Sec. 4): SDF queries per second, point-decoder shapes per second,
  marching-cubes mesh time; `roofline`: this machine's float32 matmul GFLOP/s and the SDF decoder's own on one
  large batch (without and with gradients);
- `stages`: the offline pipeline (`frodo reconstruct`) on the demo bag with the decoders' work counted per
  optimiser stage (`frodo_shape.counting`): seconds, iterations, SDF queries per iteration, point-decoder shapes,
  GFLOP and the achieved rate as a fraction of the roofline; `bag_read`: reading + decoding the demo bag (messages and MB per second).
- `sparse` / `dense`: optimiser seconds per iteration against the number of views (paper Sec. 5.3, supp.
  Table "Speed comparison": sparse 0.07 s, dense 4.96 s per iteration), from `bench/bench_sparse.py` and
  `bench/bench_dense.py` (each optional: skipped with a note when absent).
- `association`: per-frame latency against the objects in view, association (`add_frame`) and box
  refinement (`refine_boxes`) separately and together (paper Sec. 5.1).
- `end_to_end`: `frodo run` of the demo bag: wall time, per-stage figures from the nodes' diagnostics
  and objects.json, the seconds from each object's confirmation (its first track) to its first code, its first
  code of `min_views` views (`code_ready`: no stage runs before) and its first fused, sparse and dense state,
  and the intervals between each node's `/diagnostics` reports (contract: at least 1 Hz), from their publish
  stamps and, separately, their arrival at a probe.
- `room`: a synthetic room of 20 objects and 300 frames (`frodo synth --objects 20 --frames 300 --seed 7777`,
  the default walk) reconstructed offline by `frodo reconstruct` as a user runs it (its own process, start-up
  included): wall seconds, objects found, false positives, CD and F1@5cm (`--quick`: 8 objects, 150 frames).
- `before`: the demo bag reconstructed offline by `frodo reconstruct` (its own process, start-up included, no
  Rerun recording) with the code of the last commit before issue 28 (speed; `BEFORE_SPEED_WORK`, exported by
  `git archive` and put first on PYTHONPATH) and with this checkout's, one after the other in the same run: wall
  seconds, their ratio, final stages and scores of both (skipped with a note outside a git checkout that holds
  that commit, e.g. a shallow clone).
- `soak` (not in the default set: minutes to an hour): `soak_frames` frames of the demo bag repeated with shifted
  stamps at `soak_rate` x real time through the whole graph; peak and growing memory per node, backlog, latency
  per frame, /diagnostics intervals (frodo_bringup.soak; OUT/soak/soak.json + soak.png).
- `optim_workers` (not in the default set: one demo run per worker count): objects per minute against the
  number of optimiser workers, 1 and 2 (frodo_bringup.bench_workers).

What it reads is found as `frodo demo` finds its bag: relative to the working directory (`repo_path`), so run it
from the repository root or pass `--bag`; never from this module's location, which in an installed package
(colcon's install/, site-packages) has no repository above it. The bench/ scripts are not installed: from
elsewhere their sections are skipped with a note. Outputs go to `--out` (default: out/bench, also relative to the
working directory).
"""
from __future__ import annotations

import importlib.util
import io
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

import numpy as np

# Relative to the working directory (repo_path): the demo bag is `frodo demo`'s default (cli_demo.DEFAULT_BAG).
BENCH_DIR = Path('bench')
DEMO_BAG = Path('bags/demo_walk.mcap')
# The last commit before issue 28 (speed): the `before` section's baseline.
BEFORE_SPEED_WORK = 'f376e48735b1aef131a020b60174c96c39bd22d3'
# Paper figures (supplementary Table "Speed comparison", 60-frame sequence; hardware not stated there).
PAPER = {'sparse_s_per_iteration': 0.07, 'dense_s_per_iteration': 4.96, 'pmo_s_per_iteration': 12.59,
         'sparse_iterations': 200, 'dense_iterations': 100}


def repo_path(relative: str | os.PathLike) -> Path:
    """Where `frodo bench` finds a repository file it reads (bags/demo_walk.mcap, bench/<name>.py): as given when
    absolute, else relative to the working directory, as `frodo demo` finds its bag; whether it exists is for the
    caller to say (`demo_bag`, `load_bench_script`)."""
    path = Path(relative)
    return path if path.is_absolute() else Path.cwd() / path


def demo_bag(bag: str | os.PathLike = DEMO_BAG) -> Path:
    """The bag the bag sections read; FileNotFoundError (recorded as the section's error) when it is not there."""
    path = repo_path(bag)
    if not path.is_file():
        raise FileNotFoundError(f'{bag} not found in {Path.cwd()} (run from the repository root, or pass --bag)')
    return path


def load_bench_script(name: str) -> ModuleType | None:
    """bench/<name>.py of the repository as a module, or None when it is not there (run elsewhere than the
    repository root, e.g. with an installed package)."""
    path = repo_path(BENCH_DIR / f'{name}.py')
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location(f'frodo_bench_{name}', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _timed(fn: Callable[[], Any], repeats: int) -> float:
    """Median seconds of `repeats` calls of fn."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _stats_ms(values_ms) -> dict[str, float]:
    a = np.asarray(values_ms, dtype=np.float64)
    return {'mean': round(float(a.mean()), 3), 'median': round(float(np.median(a)), 3),
            'p95': round(float(np.percentile(a, 95)), 3), 'max': round(float(a.max()), 3)}


# ---------------------------------------------------------------- sections
def machine_info(device: str) -> dict[str, Any]:
    """What the figures were measured on."""
    import torch
    from frodo_common.host import cpu_model, git_commit
    cpu = cpu_model()
    commit = git_commit()     # the checkout it runs in (where the bag and bench/ come from); '' outside one
    return {'host': platform.node(), 'cpu': cpu, 'logical_cpus': os.cpu_count(),
            'load_average_1min': round(os.getloadavg()[0], 2), 'torch_threads': torch.get_num_threads(),
            'device': device, 'gpu': torch.cuda.get_device_name(0) if device.startswith('cuda') else None,
            'python': platform.python_version(), 'torch': torch.__version__, 'numpy': np.__version__,
            'commit': commit, 'date_utc': time.strftime('%Y-%m-%d %H:%M', time.gmtime())}


def decoder_throughput(device: str, quick: bool) -> dict[str, Any]:
    """SDF decoder queries/s, point decoder shapes/s and mesh extraction seconds of the shipped prior."""
    import torch
    from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior
    prior = ShapePrior.load(DEFAULT_PRIOR, device=device)
    code = prior.training_codes[0].cpu().numpy()
    repeats = 2 if quick else 5
    points = np.random.default_rng(0).uniform(-1, 1, (65536, 3)).astype(np.float32)
    prior.sdf_numpy(points[:1024], code)  # warm-up
    sdf_s = _timed(lambda: prior.sdf_numpy(points, code), repeats)
    codes = prior.training_codes[:16]
    with torch.no_grad():
        prior.decode_points(codes[:1])
        points_s = _timed(lambda: prior.decode_points(codes), repeats)
    resolution = 32 if quick else 64
    mesh_s = _timed(lambda: prior.mesh(code, resolution), 1 if quick else 3)
    return {'sdf_queries_per_s': round(len(points) / sdf_s), 'sdf_batch': len(points),
            'point_decoder_shapes_per_s': round(len(codes) / points_s, 1), 'points_per_shape': 2048,
            'mesh_resolution': resolution, 'mesh_s': round(mesh_s, 3)}


def roofline(device: str, quick: bool) -> dict[str, Any]:
    """What this machine can do: a float32 matrix product's GFLOP/s (the peak a dense layer can reach here) and
    the SDF decoder's own GFLOP/s on one large batch, without and with gradients (the best case of a stage)."""
    import torch
    from frodo_shape.counting import sdf_flops_per_query
    from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior
    n = 1024 if quick else 2048
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)

    def product() -> None:
        torch.mm(a, b)
        if device.startswith('cuda'):
            torch.cuda.synchronize()
    product()
    matmul_s = min(_timed(product, 1) for _ in range(3 if quick else 5))
    prior = ShapePrior.load(DEFAULT_PRIOR, device=device)
    flops = sdf_flops_per_query(prior.decoder.sdf_net)
    code = torch.as_tensor(prior.training_codes[:1], dtype=torch.float32, device=device)
    xyz = torch.rand(1, 32768, 3, device=device) * 2 - 1

    def forward() -> None:
        with torch.inference_mode():
            prior.decoder.sdf(code, xyz)

    def forward_backward() -> None:
        x = xyz.clone().requires_grad_(True)
        prior.decoder.sdf(code, x).sum().backward()
    forward()
    forward_backward()
    fwd_s = min(_timed(forward, 1) for _ in range(3))
    fb_s = min(_timed(forward_backward, 1) for _ in range(3))
    queries = xyz.shape[1]
    return {'matmul_n': n, 'matmul_gflops': round(2 * n ** 3 / matmul_s / 1e9, 1),
            'sdf_flops_per_query': flops, 'sdf_batch': queries,
            'sdf_forward_gflops': round(queries * flops / fwd_s / 1e9, 1),
            'sdf_forward_backward_gflops': round(2 * queries * flops / fb_s / 1e9, 1)}


def pipeline_stages(bag: Path, device: str, limits: dict[str, Any] | None,
                    params: list[str | os.PathLike] | tuple = ()) -> dict[str, Any]:
    """The offline pipeline (`frodo reconstruct`) on `bag` with the decoder's work counted per optimiser stage
    (frodo_shape.counting): objects, seconds, iterations, SDF queries per iteration, point-decoder shapes,
    GFLOP and the achieved GFLOP/s against this machine's matmul peak and the decoder's own (`roofline`);
    params: parameter files as for `frodo reconstruct --params` (default: the shipped defaults)."""
    from frodo_bringup.pipeline import PipelineConfig, reconstruct
    from frodo_shape.counting import DecoderCounter
    from frodo_shape.prior import ShapePrior
    bag = demo_bag(bag)
    base = PipelineConfig.from_params_files(params)
    config = replace(base, shape={**base.shape, 'device': device}, optim=replace(base.optim, device=device))
    prior = ShapePrior.load(config.optim.prior, device=device)
    counter = DecoderCounter(prior.decoder)
    ended: list[tuple[Any, Any]] = []
    started = time.perf_counter()
    with counter:
        result = reconstruct(bag, config, prior=prior, on_stage=lambda stage: ended.append((stage, counter.snapshot())))
    wall = time.perf_counter() - started
    rows: dict[str, dict[str, Any]] = {}
    previous = None
    for stage, snapshot in ended:
        work = snapshot - previous if previous is not None else snapshot
        previous = snapshot
        row = rows.setdefault(stage.stage, {'stage': stage.stage, 'objects': 0, 'seconds': 0.0, 'iterations': 0,
                                            'views': [], 'sdf_queries': 0, 'sdf_queries_with_grad': 0,
                                            'point_shapes': 0, 'gflop': 0.0})
        row['objects'] += 1
        row['seconds'] += stage.seconds
        row['iterations'] += stage.iterations
        row['views'].append(stage.views)
        row['sdf_queries'] += work.sdf_queries
        row['sdf_queries_with_grad'] += work.sdf_queries_with_grad
        row['point_shapes'] += work.point_shapes
        row['gflop'] += work.flops / 1e9
    peak = (limits or {}).get('matmul_gflops')
    decoder_peak = (limits or {}).get('sdf_forward_backward_gflops')
    out_rows = []
    for row in rows.values():
        rate = row['gflop'] / row['seconds'] if row['seconds'] > 0 else 0.0
        out_rows.append({
            **{k: v for k, v in row.items() if k != 'views'},
            'seconds': round(row['seconds'], 2), 'gflop': round(row['gflop'], 2),
            'seconds_per_object': round(row['seconds'] / row['objects'], 2),
            'mean_views': round(float(np.mean(row['views'])), 1) if row['views'] else 0,
            'sdf_queries_per_iteration': round(row['sdf_queries'] / row['iterations']) if row['iterations'] else None,
            'seconds_per_iteration': round(row['seconds'] / row['iterations'], 4) if row['iterations'] else None,
            'achieved_gflops': round(rate, 2),
            'fraction_of_matmul_peak': round(rate / peak, 4) if peak else None,
            'fraction_of_decoder_peak': round(rate / decoder_peak, 4) if decoder_peak else None})
    stages = {e.stage: 0 for e in result.estimates.values()}
    for e in result.estimates.values():
        stages[e.stage] += 1
    return {'bag': bag.name, 'wall_s': round(wall, 1), 'frames': result.frames,
            'phases_s': {k: round(v, 2) for k, v in result.seconds.items()}, 'final_stages': stages,
            'rows': out_rows, 'limits': limits or {}}


def bag_read_throughput(bag: Path) -> dict[str, Any]:
    """Scan + CDR decode + colour conversion of every image of `bag`."""
    from frodo_common import conversions as conv
    from frodo_common import topics
    from frodo_common.bag import BagReader
    bag = demo_bag(bag)
    t0 = time.perf_counter()
    reader = BagReader(bag)
    messages = list(reader.messages())
    scan_s = time.perf_counter() - t0
    for m in messages:
        msg = m.decode()
        if m.topic == topics.IMAGE:
            conv.image_to_rgb(msg)
    total_s = time.perf_counter() - t0
    size_mb = sum(len(m.data) for m in messages) / 1e6
    return {'bag': bag.name, 'messages': len(messages), 'payload_mb': round(size_mb, 2),
            'scan_s': round(scan_s, 3), 'scan_decode_convert_s': round(total_s, 3),
            'messages_per_s': round(len(messages) / total_s), 'mb_per_s': round(size_mb / total_s, 1)}


def optimiser_sweep(script: str, views: list[int], iterations: int, repeats: int, device: str) -> dict[str, Any]:
    """`measure(prior, views, iterations, repeats)` of bench/<script>.py for each number of views; a script
    with a `timing` subcommand instead (bench/bench_dense.py) is run as a process per number of views."""
    module = load_bench_script(script)
    if module is None:
        return {'skipped': f'bench/{script}.py not found'}
    if not hasattr(module, 'measure'):
        if hasattr(module, 'timing'):
            return _timing_sweep(script, views, iterations, device)
        return {'skipped': f'bench/{script}.py has neither measure(prior, views, iterations, repeats) nor timing'}
    from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior
    prior = ShapePrior.load(DEFAULT_PRIOR, device=device)
    rows = [module.measure(prior, v, iterations, repeats) for v in views]
    return {'script': f'bench/{script}.py', 'rows': rows}


def _timing_sweep(script: str, views: list[int], iterations: int, device: str) -> dict[str, Any]:
    """`python bench/<script>.py timing --views N --iterations I` for each N; its JSON's first dense row (and
    first `dense_depth` row, with depth images, where the script gives one)."""
    import torch
    rows = []
    for n in views:
        proc = subprocess.run([sys.executable, str(repo_path(BENCH_DIR / f'{script}.py')), 'timing',
                               '--views', str(n), '--iterations', str(iterations), '--device', device,
                               '--threads', str(torch.get_num_threads())],
                              capture_output=True, text=True, timeout=1800)
        if proc.returncode != 0:
            raise RuntimeError(f'{script}.py timing --views {n} failed: {proc.stderr.strip()[-500:]}')
        result = json.loads(proc.stdout[proc.stdout.index('{'):])
        dense = result['dense'][0]
        row = {'views': n, 'iterations': dense['iterations'],
               'ms_per_iteration': round(1e3 * dense['seconds_per_iteration'], 1),
               'stage_s': dense['stage_seconds'], 'sparse_stage_s': result.get('sparse_seconds')}
        if result.get('dense_depth'):        # the same object with its depth images (an RGB-D bag)
            row['ms_per_iteration_depth'] = round(1e3 * result['dense_depth'][0]['seconds_per_iteration'], 1)
        rows.append(row)
    return {'script': f'bench/{script}.py timing', 'rows': rows}


def association_latency(objects: list[int], frames: int, seed: int = 0) -> dict[str, Any]:
    """Per-frame association / box refinement latency (ms) on box-world walks with every object in view
    (the scene of bench/bench_association.py, for several object counts); also the process CPU time per frame
    (`total_cpu_ms`), which other jobs on a loaded machine inflate far less than the wall time."""
    from frodo_association.synthetic import make_scene
    from frodo_association.tracker import Associator, detections_from_instances
    rows = []
    for n in objects:
        spread = max(1.0, (n / 10) ** 0.5)   # bench_association's room for 10 objects, grown with the count
        scene = make_scene(n, seed, n_frames=frames, size=(640, 480), extent=2.0 * spread, radius=7.5 * spread,
                           sweep_deg=90.0, mask_noise=1, rot_noise_deg=0.3, trans_noise=0.01)
        dets = [detections_from_instances(f.instances) for f in scene.frames]
        assoc = Associator()
        t_assoc, t_refine, t_cpu = [], [], []
        for f, (labels, boxes) in zip(scene.frames, dets):
            c0, t0 = time.process_time(), time.perf_counter()
            assoc.add_frame(f.stamp, f.K, f.T_world_camera_observed, f.size, labels, boxes)
            t1 = time.perf_counter()
            assoc.refine_boxes()
            t_assoc.append(1e3 * (t1 - t0))
            t_refine.append(1e3 * (time.perf_counter() - t1))
            t_cpu.append(1e3 * (time.process_time() - c0))
        rows.append({'objects': n, 'frames': frames,
                     'detections_per_frame': round(float(np.mean([len(lab) for lab, _ in dets])), 2),
                     'association_ms': _stats_ms(t_assoc), 'box_refinement_ms': _stats_ms(t_refine),
                     'total_ms': _stats_ms(np.add(t_assoc, t_refine)), 'total_cpu_ms': _stats_ms(t_cpu)})
    return {'rows': rows}


def stage_latencies(confirmed: dict[int, float], reached: dict[int, dict[str, float]]) -> dict[str, list[float]]:
    """Per stage, the seconds from each object's confirmation to its first state at that stage, sorted, to its
    first fused code ('code') and to its first code of as many views as the optimiser needs ('code_ready',
    `OptimConfig.min_views`: before it no stage can run); objects that never reached a stage are left out of its
    list. Confirmation is the first of its track, code or state to reach the probe: each topic has its own
    queue, so a code (made only for a confirmed object) can arrive before the track that announced it, and a
    latency from the track alone came out negative."""
    from frodo_optim.states import STAGES
    start = {oid: min([t, *reached.get(oid, {}).values()]) for oid, t in confirmed.items()}
    return {stage: sorted(round(reached[oid][stage] - start[oid], 2) for oid in confirmed
                          if stage in reached.get(oid, {})) for stage in ('code', 'code_ready', *STAGES)}


def end_to_end(bag: Path, out: Path, rate: float) -> dict[str, Any]:
    """`frodo run` of `bag` with a probe recording every /diagnostics report; per-stage figures."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import Marker, MarkerArray

    from frodo_bringup.graph import NODES
    from frodo_bringup.run import run_bag
    from frodo_bringup.session import RosSession
    from frodo_common import conversions as conv
    from frodo_common import topics
    from frodo_optim.config import OptimConfig
    from frodo_optim.states import OBJECT_STATES, STAGES
    bag = demo_bag(bag)
    min_views = OptimConfig().min_views           # the demo run uses the default
    confirmed: dict[int, float] = {}          # object -> when its track first reached the probe
    reached: dict[int, dict[str, float]] = {}  # object -> stage -> when its state first said that stage

    def on_tracks(msg: MarkerArray) -> None:
        now = time.monotonic()
        with lock:
            for m in msg.markers:
                if m.action == Marker.ADD:
                    confirmed.setdefault(m.id, now)

    def on_states(msg: PointCloud2) -> None:
        now = time.monotonic()
        table = conv.cloud_to_table(msg)
        with lock:
            for oid, stage in zip(table['object_id'], table['stage']):
                reached.setdefault(int(oid), {}).setdefault(STAGES[int(stage)], now)

    def on_codes(msg: PointCloud2) -> None:    # the fused stage needs the object's code (shape_node) as well
        now = time.monotonic()
        with lock:
            for row in conv.cloud_to_table(msg):
                times = reached.setdefault(int(row['object_id']), {})
                times.setdefault('code', now)
                if int(row['num_views']) >= min_views:
                    times.setdefault('code_ready', now)
    arrivals: dict[str, list[float]] = {}     # when the probe received each report
    sent: dict[str, list[float]] = {}         # header stamps: when the node published it
    last: dict[str, dict[str, str]] = {}
    lock = threading.Lock()

    def on_diagnostics(msg: DiagnosticArray) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        with lock:
            for status in msg.status:
                arrivals.setdefault(status.name, []).append(now)
                sent.setdefault(status.name, []).append(stamp)
                last[status.name] = {kv.key: kv.value for kv in status.values}

    log = io.StringIO()
    with RosSession('frodo_bench_probe') as probe:
        probe.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diagnostics, 100)
        probe.node.create_subscription(MarkerArray, topics.TRACKS, on_tracks, topics.LATCHED_QOS)
        probe.node.create_subscription(PointCloud2, OBJECT_STATES, on_states, topics.LATCHED_QOS)
        probe.node.create_subscription(PointCloud2, topics.OBJECT_CODES, on_codes, topics.LATCHED_QOS)
        result = run_bag(bag, out, rate=rate, output=log, progress=False, timeout=600)
    (out / 'run.log').write_text(log.getvalue())
    names = [n.name for n in NODES]
    intervals = {}

    def gap_stats(times: list[float]) -> dict[str, float]:
        gaps = np.diff(times[1:]) if len(times) > 2 else np.zeros(0)  # the first report comes at start-up
        if not len(gaps):
            return {}
        return {'mean_s': round(float(gaps.mean()), 3), 'p95_s': round(float(np.percentile(gaps, 95)), 3),
                'max_s': round(float(gaps.max()), 3), 'over_1_5_s': int(np.sum(gaps > 1.5))}
    with lock:
        for name in names:
            # Publish times show the node's own schedule; arrival times add the probe's (loaded) delays.
            intervals[name] = {'reports': len(sent.get(name, [])), **gap_stats(sent.get(name, [])),
                               'arrival': gap_stats(arrivals.get(name, []))}
        assoc = last.get('association_node', {})
        shape = last.get('shape_node', {})
        latency = stage_latencies(confirmed, reached)
    optimiser_s = [r.get('timings', {}).get('optimiser_s') for r in result.records]
    optimiser_s = [s for s in optimiser_s if s is not None]
    bag_s = result.play.seconds if result.play is not None else None
    return {'bag': bag.name, 'rate': rate, 'exit_code': result.exit_code,
            'failures': [f.describe().splitlines()[0] for f in result.failures], 'objects': len(result.records),
            'wall_s': round(result.seconds, 2), 'playback_s': round(bag_s, 2) if bag_s is not None else None,
            'done_after_bag_s': round(result.done_after_bag_s, 2) if result.done_after_bag_s is not None else None,
            'stages': {
                'association_ms_per_frame_mean': assoc.get('association_ms_mean'),
                'association_ms_per_frame_max': assoc.get('association_ms_max'),
                'shape_crops_encoded': shape.get('crops_encoded'),
                'optimiser_s_per_object': [round(s, 2) for s in optimiser_s],
                'optimiser_s_total': round(float(sum(optimiser_s)), 2)},
            'confirmation_to_stage_s': latency,
            'diagnostics_intervals': intervals}


# ---------------------------------------------------------------- plots
def write_plots(doc: dict[str, Any], out: Path) -> list[str]:
    """PNG figures of the sweeps; returns the file names written."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    written = []
    machine = doc['machine']
    subtitle = f"{machine['cpu']} ({machine['logical_cpus']} CPUs, load {machine['load_average_1min']}), {machine['device']}"
    optim = [(k, doc[k]['rows']) for k in ('sparse', 'dense') if 'rows' in doc.get(k, {})]
    if optim:
        fig, ax = plt.subplots(figsize=(6, 4))
        for key, rows in optim:
            ax.plot([r['views'] for r in rows], [r['ms_per_iteration'] / 1e3 for r in rows], 'o-', label=key)
            ax.axhline(PAPER[f'{key}_s_per_iteration'], ls='--', lw=0.8, color=ax.lines[-1].get_color(),
                       label=f'{key}, paper')
        ax.set(xlabel='views', ylabel='seconds per iteration', yscale='log', title=f'optimiser\n{subtitle}')
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / 'optimiser.png', dpi=100)
        plt.close(fig)
        written.append('optimiser.png')
    if 'rows' in doc.get('association', {}):
        rows = doc['association']['rows']
        fig, ax = plt.subplots(figsize=(6, 4))
        for key, label in (('association_ms', 'association'), ('box_refinement_ms', 'box refinement'),
                           ('total_ms', 'together')):
            ax.plot([r['objects'] for r in rows], [r[key]['mean'] for r in rows], 'o-', label=f'{label} (mean)')
        ax.plot([r['objects'] for r in rows], [r['total_ms']['p95'] for r in rows], 'k:', label='together (p95)')
        ax.set(xlabel='objects in view', ylabel='ms per frame', title=f'association\n{subtitle}')
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / 'association.png', dpi=100)
        plt.close(fig)
        written.append('association.png')
    intervals = doc.get('end_to_end', {}).get('diagnostics_intervals', {})
    named = [(n, v) for n, v in intervals.items() if 'max_s' in v]
    if named:
        fig, ax = plt.subplots(figsize=(6, 4))
        x = np.arange(len(named))
        for offset, key in ((-0.27, 'mean_s'), (0.0, 'p95_s'), (0.27, 'max_s')):
            ax.bar(x + offset, [v[key] for _, v in named], 0.27, label=key[:-2])
        ax.axhline(1.0, ls='--', color='k', lw=0.8, label='contract: 1 s')
        ax.set_xticks(x, [n for n, _ in named], rotation=15)
        ax.set(ylabel='seconds between /diagnostics reports', title=f'diagnostics during the demo run\n{subtitle}')
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / 'diagnostics.png', dpi=100)
        plt.close(fig)
        written.append('diagnostics.png')
    return written


def synthetic_room(out: Path, objects: int, frames: int, seed: int = 7777) -> dict[str, Any]:
    """`frodo synth` a room of `objects` objects over `frames` frames, then time `frodo reconstruct` of it (a
    process of its own, as a user runs it) and read its scores (eval.json, CONTRACT.md protocol)."""
    out.mkdir(parents=True, exist_ok=True)
    bag = out / f'room{objects}.mcap'
    subprocess.run([sys.executable, '-m', 'frodo_bringup.cli', 'synth', str(bag), '--objects', str(objects),
                    '--frames', str(frames), '--seed', str(seed), '--quiet'],
                   check=True, capture_output=True, text=True)
    run = _reconstruct_timed(bag, out / 'reconstruct', options=('--no-recording',))
    return {'objects': objects, 'frames': frames, 'seed': seed} | {k: run[k] for k in (
        'wall_s', 'found', 'ground_truth', 'false_positives', 'cd_cm', 'f1')}


def _reconstruct_timed(bag: Path, out: Path, env: dict[str, str] | None = None,
                       options: tuple[str, ...] = ()) -> dict[str, Any]:
    """`frodo reconstruct BAG --out OUT --quiet [options]` in a process of its own: wall seconds (start-up
    included), the final stages and the CONTRACT.md scores of its eval.json (RuntimeError when it fails)."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, '-m', 'frodo_bringup.cli', 'reconstruct', str(bag), '--out', str(out),
                           '--quiet', *options], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f'frodo reconstruct exited {done.returncode}: {done.stdout[-400:]}{done.stderr[-400:]}')
    stages: dict[str, int] = {}
    for obj in json.loads((out / 'objects.json').read_text())['objects']:
        stages[obj['stage']] = stages.get(obj['stage'], 0) + 1
    overall = json.loads((out / 'eval.json').read_text())['overall'] if (out / 'eval.json').is_file() else {}
    def rounded(key: str, digits: int) -> float | None:
        return None if key not in overall else round(overall[key], digits)

    return {'wall_s': round(wall, 1), 'final_stages': stages, 'found': overall.get('n_matched'),
            'ground_truth': overall.get('n_gt'), 'false_positives': overall.get('false_positives'),
            'cd_cm': rounded('cd_cm', 2), 'f1': rounded('f1', 1)}


def before_and_now(bag: Path, out: Path, revision: str = BEFORE_SPEED_WORK) -> dict[str, Any]:
    """The `before` section (module docstring): the same bag reconstructed offline by the code of `revision` and
    by this checkout's, in that order."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(['git', *args], capture_output=True)

    try:
        known = git('cat-file', '-e', f'{revision}^{{commit}}').returncode == 0
    except FileNotFoundError:
        known = False
    if not known:
        return {'skipped': f'commit {revision[:10]} is not in a git checkout here (run from a full clone of the '
                           'repository)'}
    code = out / 'code'
    shutil.rmtree(code, ignore_errors=True)
    code.mkdir(parents=True)
    archive = git('archive', revision)
    if archive.returncode != 0:
        return {'error': f'git archive {revision[:10]} failed: {archive.stderr.decode()[-300:]}'}
    subprocess.run(['tar', '-x', '-C', str(code)], input=archive.stdout, check=True)
    packages = sorted(str(p) for p in (code / 'src').glob('frodo_*') if (p / p.name).is_dir())
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(packages + [os.environ.get('PYTHONPATH', '')]).rstrip(os.pathsep))
    before = _reconstruct_timed(bag, out / 'before', env)
    now = _reconstruct_timed(bag, out / 'now')
    return {'bag': str(bag), 'revision': revision[:10], 'code': str(code), 'before': before, 'now': now,
            'speed_up': round(before['wall_s'] / now['wall_s'], 2)}


def run_all(out: Path, quick: bool, device: str, sections: list[str], log: Callable[[str], None],
            soak_frames: int = 10_000, soak_rate: float = 2.0, bag: str | os.PathLike = DEMO_BAG) -> dict[str, Any]:
    """Every requested section, each timed and isolated (an exception is recorded, the others still run);
    `bag` (relative to the working directory unless absolute) feeds bag_read, end_to_end, soak and optim_workers."""
    out.mkdir(parents=True, exist_ok=True)
    views = [5, 35] if quick else [5, 10, 20, 35, 60]
    plan: dict[str, Callable[[], dict[str, Any]]] = {
        'decoder': lambda: decoder_throughput(device, quick),
        'roofline': lambda: roofline(device, quick),
        'stages': lambda: pipeline_stages(bag, device, doc.get('roofline')),
        'bag_read': lambda: bag_read_throughput(bag),
        'sparse': lambda: optimiser_sweep('bench_sparse', views, 10 if quick else 30, 1 if quick else 3, device),
        'dense': lambda: optimiser_sweep('bench_dense', [5, 10] if quick else [5, 10, 20, 35], 2 if quick else 3,
                                         1, device),
        'association': lambda: association_latency([2, 10] if quick else [1, 2, 5, 10, 20], 40 if quick else 200),
        'end_to_end': lambda: end_to_end(bag, out / 'demo_run', rate=1.0),
        'room': lambda: synthetic_room(out / 'room', *((8, 150) if quick else (20, 300))),
        'before': lambda: before_and_now(demo_bag(bag), out / 'before'),
        'soak': lambda: _soak(demo_bag(bag), out / 'soak', soak_frames, soak_rate, doc['machine'], log),
        'optim_workers': lambda: _optim_workers(demo_bag(bag), out / 'optim_workers', quick, log),
    }
    doc: dict[str, Any] = {'machine': machine_info(device), 'quick': quick, 'paper': PAPER}
    for name in sections:
        log(f'{name} ...')
        t0 = time.perf_counter()
        try:
            doc[name] = plan[name]()
        except Exception as err:  # noqa: BLE001 - one failing section must not lose the others
            doc[name] = {'error': f'{type(err).__name__}: {err}'}
        doc[name]['section_s'] = round(time.perf_counter() - t0, 1)
        log(f'{name}: done in {doc[name]["section_s"]} s' + (f' ({doc[name]["error"]})' if 'error' in doc[name]
                                                              else f' ({doc[name]["skipped"]})'
                                                              if 'skipped' in doc[name] else ''))
    doc['machine']['load_average_1min_end'] = round(os.getloadavg()[0], 2)
    doc['plots'] = write_plots(doc, out) + (['soak/soak.png'] if 'plot' in doc.get('soak', {}) else [])
    return doc


def _soak(bag: Path, out: Path, frames: int, rate: float, machine: dict[str, Any],
          log: Callable[[str], None]) -> dict[str, Any]:
    from frodo_bringup.soak import soak
    subtitle = f"{machine['cpu']} ({machine['logical_cpus']} CPUs, load {machine['load_average_1min']})"
    return soak(out, frames=frames, rate=rate, bag=bag, subtitle=subtitle, log=log)


def _optim_workers(bag: Path, out: Path, quick: bool, log: Callable[[str], None]) -> dict[str, Any]:
    from frodo_bringup.bench_workers import objects_per_minute
    return objects_per_minute(bag, out, workers=(1, 2), rate=1.0, quick=quick, log=log)


SECTIONS = ('decoder', 'roofline', 'stages', 'bag_read', 'sparse', 'dense', 'association', 'end_to_end',
            'room', 'before')   # default
ALL_SECTIONS = SECTIONS + ('soak', 'optim_workers')


def summary(doc: dict[str, Any]) -> str:
    """A short human-readable table of the headline figures."""
    lines = []
    m = doc['machine']
    lines.append(f"machine: {m['cpu']}, {m['logical_cpus']} logical CPUs, load {m['load_average_1min']} -> "
                 f"{m.get('load_average_1min_end')}, torch threads {m['torch_threads']}, device {m['device']}")
    d = doc.get('decoder', {})
    if 'sdf_queries_per_s' in d:
        lines.append(f"decoder: {d['sdf_queries_per_s']:,} SDF queries/s, {d['point_decoder_shapes_per_s']} "
                     f"point-decoder shapes/s, mesh at {d['mesh_resolution']}^3 in {d['mesh_s']} s")
    r = doc.get('roofline', {})
    if 'matmul_gflops' in r:
        lines.append(f"roofline: float32 matmul {r['matmul_gflops']} GFLOP/s ({r['matmul_n']}^2); SDF decoder "
                     f"{r['sdf_flops_per_query']:,} FLOP/query, {r['sdf_forward_gflops']} GFLOP/s forward, "
                     f"{r['sdf_forward_backward_gflops']} with gradients (batch {r['sdf_batch']:,})")
    st = doc.get('stages', {})
    if 'rows' in st:
        lines.append(f"pipeline on {st['bag']}: {st['wall_s']} s ({', '.join(f'{k} {v} s' for k, v in st['phases_s'].items())}); "
                     f"final stages {st['final_stages']}")
        for row in st['rows']:
            frac = row['fraction_of_matmul_peak']
            lines.append(f"  {row['stage']:>6}: {row['objects']} objects, {row['seconds_per_object']} s each, "
                         f"{row['iterations']} iterations, {row['mean_views']} views, "
                         f"{row['sdf_queries_per_iteration'] or '-'} SDF queries/iteration, {row['point_shapes']} "
                         f"point-decoder shapes, {row['gflop']} GFLOP at {row['achieved_gflops']} GFLOP/s"
                         + (f" = {100 * frac:.1f} % of the matmul peak" if frac is not None else ''))
    b = doc.get('bag_read', {})
    if 'messages_per_s' in b:
        lines.append(f"bag read+decode: {b['messages_per_s']:,} messages/s, {b['mb_per_s']} MB/s ({b['bag']})")
    for key in ('sparse', 'dense'):
        sec = doc.get(key, {})
        if 'rows' in sec:
            per = ', '.join(f"{r['views']} views {r['ms_per_iteration']:.1f} ms"
                            + (f" ({r['ms_per_iteration_depth']:.1f} with depth)" if 'ms_per_iteration_depth' in r
                               else '') for r in sec['rows'])
            lines.append(f"{key} per iteration: {per} (paper: {PAPER[f'{key}_s_per_iteration'] * 1e3:.0f} ms)")
        elif sec:
            lines.append(f"{key}: {sec.get('skipped') or sec.get('error')}")
    a = doc.get('association', {})
    for r in a.get('rows', []):
        lines.append(f"association, {r['objects']:2d} objects ({r['detections_per_frame']} in view): "
                     f"add_frame {r['association_ms']['mean']:.2f} ms, refine_boxes {r['box_refinement_ms']['mean']:.2f}"
                     f" ms, together {r['total_ms']['mean']:.2f} ms mean / {r['total_ms']['p95']:.2f} ms p95"
                     f" (CPU time {r['total_cpu_ms']['mean']:.2f} / {r['total_cpu_ms']['p95']:.2f} ms)")
    room = doc.get('room', {})
    if 'wall_s' in room:
        lines.append(f"synthetic room, {room['objects']} objects / {room['frames']} frames: frodo reconstruct "
                     f"{room['wall_s']} s wall, {room['found']}/{room['ground_truth']} found, "
                     f"{room['false_positives']} FP, CD {room['cd_cm']} cm, F1@5cm {room['f1']}")
    elif room:
        lines.append(f"synthetic room: {room.get('error')}")
    b = doc.get('before', {})
    if 'speed_up' in b:
        lines.append(f"offline demo, code before issue 28 ({b['revision']}) -> now: {b['before']['wall_s']} -> "
                     f"{b['now']['wall_s']} s wall ({b['speed_up']}x), F1@5cm {b['before']['f1']} -> {b['now']['f1']}, "
                     f"CD {b['before']['cd_cm']} -> {b['now']['cd_cm']} cm, final stages {b['before']['final_stages']} "
                     f"-> {b['now']['final_stages']}")
    elif b:
        lines.append(f"before/now: {b.get('skipped') or b.get('error')}")
    e = doc.get('end_to_end', {})
    if 'wall_s' in e:
        lines.append(f"demo run: exit {e['exit_code']}, {e['objects']} objects, {e['wall_s']} s wall "
                     f"({e['playback_s']} s playing, done {e.get('done_after_bag_s')} s after it); association "
                     f"{e['stages']['association_ms_per_frame_mean']} ms "
                     f"per frame; optimiser {e['stages']['optimiser_s_total']} s over all objects")
        for stage, values in e.get('confirmation_to_stage_s', {}).items():
            if values:
                lines.append(f"  confirmation -> {stage}: {', '.join(f'{v} s' for v in values)} (per object)")
        for name, v in e['diagnostics_intervals'].items():
            if 'max_s' in v:
                lines.append(f"  /diagnostics {name}: {v['reports']} reports, every {v['mean_s']} s on average, "
                             f"p95 {v['p95_s']} s, max {v['max_s']} s, {v['over_1_5_s']} gaps > 1.5 s "
                             f"(at the probe: max {v['arrival'].get('max_s')} s)")
    s = doc.get('soak', {})
    if 'memory' in s:
        lines.append(f"soak: {s['frames_played']} frames at {s['rate']}x, exit {s['exit_code']}, {s['objects']} objects, "
                     f"{s['wall_s']} s wall; per-frame latency median {s['latency'].get('median_ms')} ms, p95 "
                     f"{s['latency'].get('p95_ms')} ms (last/first tenth {s['latency'].get('last_to_first_tenth_median')})")
        for name, m in s['memory'].items():
            lines.append(f"  {name}: RSS peak {m['peak_mb']} MB, end {m['end_mb']} MB, growth over the second half "
                         f"{m['growth_mb_per_1000_frames']} MB per 1000 frames; backlog max "
                         f"{s['backlog_frames'].get(name, {}).get('max')} frames")
    for r in doc.get('optim_workers', {}).get('rows', []):
        lines.append(f"optimiser workers {r['workers']}: {r['objects']} objects ({', '.join(r['stages'])}), "
                     f"{r['objects_per_minute']} objects/min ({r['first_image_to_last_map_s']} s from the first image "
                     f"to the last map change, {r['wall_s']} s wall, exit {r['exit_code']}) on "
                     f"{doc['optim_workers']['cpu_cores']} CPUs")
    return '\n'.join(lines)


def _cell(value: Any) -> str:
    return '-' if value is None else f'{value:,}' if isinstance(value, int) else str(value)


def markdown_page(doc: dict[str, Any], plots_dir: str) -> str:
    """The benchmark as a page (`frodo bench --page`): machine and commit, the offline pipeline's work per stage
    against this machine's roofline, the optimisers per iteration against the paper, association latency, the
    live demo run; plots_dir: where the page finds the plots (relative to the page)."""
    m = doc['machine']
    lines = ['# Performance', '',
             f"Generated by `frodo bench{' --quick' if doc.get('quick') else ''} --page` on {m['date_utc']} UTC, "
             f"commit `{m.get('commit_key') or m.get('commit') or 'unknown'}`. Machine: {m['cpu']}, {m['logical_cpus']} logical CPUs, "
             f"torch {m['torch']} ({m['torch_threads']} threads), device {m['device']}"
             + (f" ({m['gpu']})" if m.get('gpu') else '') + f"; 1-minute load {m['load_average_1min']} at the start, "
             f"{m.get('load_average_1min_end')} at the end (above the CPU count, the figures are slower than the "
             f"machine can do). Regenerate: `frodo bench --page docs/performance.md`.", '']
    r = doc.get('roofline', {})
    if 'matmul_gflops' in r:
        lines += [f"Roofline, measured in the same run: float32 matmul {r['matmul_gflops']} GFLOP/s "
                  f"({r['matmul_n']}^2); the SDF decoder ({r['sdf_flops_per_query']:,} FLOP per query) "
                  f"{r['sdf_forward_gflops']} GFLOP/s forward, {r['sdf_forward_backward_gflops']} with gradients "
                  f"(batch {r['sdf_batch']:,}).", '']
    st = doc.get('stages', {})
    if 'rows' in st:
        phases = ', '.join(f'{k} {v} s' for k, v in st['phases_s'].items())
        lines += [f"## Offline pipeline (`frodo reconstruct {st['bag']}`)", '',
                  f"{st['wall_s']} s in all ({phases}); final stages {st['final_stages']}.", '',
                  '| stage | objects | s per object | iterations | mean views | SDF queries per iteration '
                  '| s per iteration | GFLOP | GFLOP/s | of the matmul peak | of the decoder peak |',
                  '|---|---|---|---|---|---|---|---|---|---|---|']
        for row in st['rows']:
            pct = [None if row[k] is None else f'{100 * row[k]:.1f} %'
                   for k in ('fraction_of_matmul_peak', 'fraction_of_decoder_peak')]
            lines.append('| ' + ' | '.join(_cell(v) for v in (
                row['stage'], row['objects'], row['seconds_per_object'], row['iterations'], row['mean_views'],
                row['sdf_queries_per_iteration'], row['seconds_per_iteration'], row['gflop'],
                row['achieved_gflops'], *pct)) + ' |')
        lines.append('')
    for key in ('sparse', 'dense'):
        sec = doc.get(key, {})
        if 'rows' in sec:
            paper = PAPER[f'{key}_s_per_iteration'] * 1e3
            rows = [row for row in sec['rows'] if row.get('ms_per_iteration')]
            depth = bool(rows) and all(row.get('ms_per_iteration_depth') for row in rows)
            header = '| views | ms per iteration | paper (GPU) / this |' + (' with depth images: ms |' if depth else '')
            lines += [f'## {key.capitalize()} stage per iteration (one object, `bench/bench_{key}.py timing`)', '',
                      header, '|---|---|---|' + ('---|' if depth else '')]
            lines += [f"| {row['views']} | {row['ms_per_iteration']:.1f} | {paper / row['ms_per_iteration']:.1f}x |"
                      + (f" {row['ms_per_iteration_depth']:.1f} |" if depth else '') for row in rows]
            lines += ['', f'Paper: {paper:.0f} ms per iteration (supplement, "Speed comparison"; hardware not '
                      'stated there).', '']
    a = doc.get('association', {})
    if a.get('rows'):
        lines += ['## Association per frame (`add_frame` + `refine_boxes`)', '',
                  '| objects | in view | mean ms | p95 ms | CPU ms (mean) |', '|---|---|---|---|---|']
        lines += [f"| {row['objects']} | {row['detections_per_frame']} | {row['total_ms']['mean']:.2f} | "
                  f"{row['total_ms']['p95']:.2f} | {row['total_cpu_ms']['mean']:.2f} |" for row in a['rows']]
        lines.append('')
    room = doc.get('room', {})
    if 'wall_s' in room:
        lines += [f"## Synthetic room of {room['objects']} objects (`frodo reconstruct`, offline)", '',
                  f"`frodo synth --objects {room['objects']} --frames {room['frames']} --seed {room['seed']}`: "
                  f"{room['wall_s']} s wall for `frodo reconstruct` (start-up included); {room['found']} of "
                  f"{room['ground_truth']} objects found, {room['false_positives']} false positives, CD "
                  f"{room['cd_cm']} cm, F1@5cm {room['f1']}.", '']
    b = doc.get('before', {})
    if 'speed_up' in b:
        lines += ['## Before the speed work (issue 28), measured in this run', '',
                  f"`frodo reconstruct {Path(b['bag']).name}` (a process of its own, start-up included) with the code "
                  f"of commit `{b['revision']}`, the last before issue 28, then with this checkout's:", '',
                  '| code | wall s | final stages | found | CD cm | F1@5cm |', '|---|---|---|---|---|---|']
        for name, label in (('before', f"`{b['revision']}` (before)"), ('now', 'this checkout')):
            r = b[name]
            stages = ', '.join(f'{n} {k}' for k, n in r['final_stages'].items())
            lines.append(f"| {label} | {r['wall_s']} | {stages} | {r['found']} of {r['ground_truth']} | "
                         f"{r['cd_cm']} | {r['f1']} |")
        lines += ['', f"Speed-up: {b['speed_up']}x.", '']
    e = doc.get('end_to_end', {})
    if 'wall_s' in e:
        lines += ['## Live demo run (`frodo run`, real time)', '',
                  f"{e['objects']} objects, {e['wall_s']} s wall of which {e['playback_s']} s playing the bag "
                  f"(exit {e['exit_code']}); done {e.get('done_after_bag_s')} s after the bag's last message; "
                  f"optimiser {e['stages']['optimiser_s_total']} s over all objects.", '']
        latencies = {k: v for k, v in e.get('confirmation_to_stage_s', {}).items() if v}
        if latencies:
            lines += ['| from confirmation to | seconds per object |', '|---|---|']
            lines += [f"| {stage} | {', '.join(str(v) for v in values)} |" for stage, values in latencies.items()]
            lines += ['', 'Confirmation: the first of the object\'s track, code or state to reach a listening node.', '']
    lines += [f'![{p}]({plots_dir}/{p})' for p in doc.get('plots', []) if p.endswith('.png')]
    return '\n'.join(lines).rstrip() + '\n'
