"""The whole method on a recorded bag, synchronous and without ROS processes (`frodo reconstruct`).

The same layers the nodes adapt, called in order (paper Sec. 5): detection filter or Mask R-CNN
(`frodo_detection.config`) -> association with surface evidence (`frodo_association.frames.FrameAssociator`) ->
encoder + code fusion (`frodo_shape.encoding.CodeEncoder`) -> per-object fused -> sparse -> dense
(`frodo_optim.reconstructor.ObjectReconstructor`). Offline the whole bag is known before shape inference, so:

1. pass 1 associates every frame, then fits the boxes of every object to all its detections;
2. pass 2 encodes each kept detection and stores its views under the association's final ids;
3. each object is reconstructed once, by id, with all its views; with `workers` > 1 the objects are shared out
   among that many processes (each with its share of torch's threads), so a machine with more cores refines
   several objects at once.

The live graph converges to the same object map when its optimiser catches up; offline nothing waits for the
clock, and the result depends only on the bag and the configuration: same inputs, same `objects.json` (timings
aside; bit for bit when MKL is asked for reproducible results before torch is imported, as `frodo reconstruct`
does: `frodo_common.host.reproducible_math()`). Python use:

    from frodo_common.host import reproducible_math; reproducible_math()   # first, before torch
    from frodo_bringup.pipeline import PipelineConfig, reconstruct
    result = reconstruct('bags/demo_walk.mcap', PipelineConfig.from_params_files(['my.yaml']))
    result.write('out/offline')          # objects.json + meshes/, as `frodo run --out` writes them
    for record in result.records(): ...
"""
from __future__ import annotations

import json
import math
import os
import time
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from frodo_association.config import AssociationConfig, EvidenceConfig
from frodo_association.frames import FrameAssociator, config_from_values
from frodo_bringup.outputs import MESH_DIR, OBJECTS_FILE, _file_stem, write_ply
from frodo_bringup.preflight import check_bag
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.categories import category_by_id
from frodo_common.frames import depth_to_metres
from frodo_detection.config import PARAMS as DETECTION_PARAMS, filter_config, make_detector
from frodo_detection.core import filter_instances
from frodo_optim.config import PARAMS as OPTIM_PARAMS, OptimConfig, optim_config
from frodo_optim.core import ObjectEstimate
from frodo_optim.reconstructor import ObjectInput, ObjectOutcome, ObjectReconstructor, Scene, StageOutcome
from frodo_optim.states import estimates_table, states_to_records
from frodo_optim.views import ViewMemory
from frodo_shape.encoding import PARAMS as SHAPE_PARAMS, CodeEncoder
from frodo_shape.prior import ShapePrior

class PipelineError(RuntimeError):
    """The configuration is invalid or a layer failed (a bag that cannot give objects: `preflight.BagRefused`)."""


def offline_optim_config(config: OptimConfig | None = None) -> OptimConfig:
    """The optimiser's configuration offline: the node's, without the dense stage's wall-clock bound
    (`dense_max_seconds`), which keeps a live graph's latency bounded but would make a result depend on how
    loaded the machine is; iterations bound the work instead."""
    config = config or OptimConfig()
    return replace(config, dense=replace(config.dense, max_seconds=math.inf))


@dataclass
class PipelineConfig:
    """Configuration of every layer; defaults are the nodes' defaults, except that the dense stage has no
    wall-clock bound unless a parameter file sets `dense_max_seconds` (`offline_optim_config`). `detection` and
    `shape` hold parameter values by name (`frodo_detection.config.PARAMS`, `frodo_shape.encoding.PARAMS`)."""

    detection: dict[str, Any] = field(default_factory=dict)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    shape: dict[str, Any] = field(default_factory=dict)
    optim: OptimConfig = field(default_factory=offline_optim_config)
    world_frame: str = 'world'

    @classmethod
    def from_params_files(cls, params_files: Sequence[str | os.PathLike] = ()) -> 'PipelineConfig':
        """The configuration a `frodo run --params FILE ...` graph would run with (node sections
        `detection_node`, `association_node`, `shape_node`, `optim_node`; later files win; preset names such as
        `keyframes` allowed). Topic, worker and map parameters of the nodes have no meaning offline and are
        ignored."""
        from frodo_bringup.graph import resolve_params_file, section_parameters
        files = [resolve_params_file(f) for f in params_files]
        sections = {name: section_parameters(files, name)
                    for name in ('detection_node', 'association_node', 'shape_node', 'optim_node')}
        optim_names = {spec.name for spec in OPTIM_PARAMS}
        world = next((s['world_frame'] for s in sections.values() if 'world_frame' in s), 'world')
        association, evidence = config_from_values(sections['association_node'])
        try:
            optim = optim_config({k: v for k, v in sections['optim_node'].items() if k in optim_names})
            if 'dense_max_seconds' not in sections['optim_node']:
                optim = offline_optim_config(optim)
            filter_config(sections['detection_node'])
        except (ValueError, TypeError) as err:
            raise PipelineError(f'parameters: {err}') from err
        return cls(detection={k: v for k, v in sections['detection_node'].items()
                              if k in {s.name for s in DETECTION_PARAMS}},
                   association=association, evidence=evidence,
                   shape={k: v for k, v in sections['shape_node'].items() if k in {s.name for s in SHAPE_PARAMS}},
                   optim=optim, world_frame=str(world))


@dataclass
class Frame:
    """One input frame of a bag: stamp (ns), intrinsics K (3, 3), size (W, H), T_world_camera (4, 4), rgb
    (H, W, 3) uint8 (None when not asked for), raw instance image (H, W) uint16 or None, depth (H, W) metres or None, the latest SLAM map
    (N, 3) or None."""

    stamp: int
    K: np.ndarray
    size: tuple[int, int]
    T_world_camera: np.ndarray
    rgb: np.ndarray | None
    instances: np.ndarray | None
    depth_m: np.ndarray | None
    landmarks: np.ndarray | None


@dataclass
class ObjectMap:
    """What `reconstruct` found: every object's estimate, each object's stage outcomes, the bag's problems
    (skipped frames and messages) and the seconds each phase took."""

    estimates: dict[int, ObjectEstimate]
    outcomes: dict[int, ObjectOutcome]
    world_frame: str = 'world'
    frames: int = 0
    has_ground_truth: bool = False     # the bag has /ground_truth/objects (evaluation only, never read here)
    problems: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    tracks: dict[int, tuple[str, tuple]] = field(default_factory=dict)   # the association's final boxes
    associations: dict[int, np.ndarray] = field(default_factory=dict)    # per frame stamp: ASSOCIATION_DTYPE rows

    def records(self) -> list[dict[str, Any]]:
        """One objects.json record per object, by id (CONTRACT.md "Files written by the command line")."""
        estimates = [self.estimates[oid] for oid in sorted(self.estimates)]
        records = states_to_records(estimates_table(estimates))
        out = []
        for est in estimates:
            record = records[est.object_id]
            record['class'] = est.class_name
            record['mesh'] = f'{MESH_DIR}/{_file_stem(est.object_id, est.class_name)}.ply'
            record['mesh_faces'] = int(len(est.mesh_world.faces))
            out.append(record)
        return out

    def write(self, out_dir: str | os.PathLike) -> list[dict[str, Any]]:
        """objects.json and meshes/<id>_<class>.ply (world frame) under out_dir; returns the records. The Rerun
        recording: `frodo_bringup.recording.write_recording(bag, object_map, path)`."""
        out = Path(out_dir)
        (out / MESH_DIR).mkdir(parents=True, exist_ok=True)
        records = self.records()
        for record in records:
            mesh = self.estimates[record['id']].mesh_world
            write_ply(out / record['mesh'], np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces))
        document = {'frame_id': self.world_frame, 'objects': records}
        (out / OBJECTS_FILE).write_text(json.dumps(document, indent=2) + '\n')
        return records


def bag_frames(reader: BagReader, need_instances: bool, with_rgb: bool = True) -> Iterator[Frame]:
    """The bag's complete frames in stamp order (image + pose, + instances when `need_instances`; camera info
    seen before or with the frame). Depth and the latest landmarks are attached when present; the colour image
    is decoded only `with_rgb` (its presence still counts)."""
    wanted = [topics.IMAGE, topics.CAMERA_INFO, topics.POSE, topics.INSTANCES, topics.DEPTH, topics.SLAM_POINTS]
    camera, landmarks = None, None
    parts: dict[int, dict[str, Any]] = {}
    required = ('image', 'pose') + (('instances',) if need_instances else ())

    def complete(stamp: int) -> Frame | None:
        frame = parts.pop(stamp)
        if camera is None or not all(k in frame for k in required):
            return None
        return Frame(stamp, camera[0], camera[1], frame['pose'], frame['image'], frame.get('instances'),
                     frame.get('depth'), landmarks)

    for m in reader.messages(wanted):
        msg = m.decode()
        if m.topic == topics.SLAM_POINTS:
            points = conv.cloud_to_xyz(msg)
            landmarks = points[np.isfinite(points).all(1)] if len(points) else None
            continue
        stamp = conv.stamp_to_ns(msg.header.stamp)
        for done in [s for s in parts if s < stamp]:   # stamps are in order: earlier frames are complete
            frame = complete(done)
            if frame is not None:
                yield frame
        try:
            if m.topic == topics.CAMERA_INFO:
                camera = (conv.camera_info_to_K(msg), (int(msg.width), int(msg.height)))
            elif m.topic == topics.IMAGE:
                parts.setdefault(stamp, {})['image'] = conv.image_to_rgb(msg) if with_rgb else None
            elif m.topic == topics.POSE:
                parts.setdefault(stamp, {})['pose'] = conv.pose_to_matrix(msg.pose)
            elif m.topic == topics.INSTANCES:
                if msg.encoding != '16UC1':
                    raise conv.ConversionError(f'instances encoding must be 16UC1, got {msg.encoding!r}')
                parts.setdefault(stamp, {})['instances'] = conv.image_to_numpy(msg)
            else:
                if msg.encoding not in ('16UC1', '32FC1'):
                    raise conv.ConversionError(f'depth encoding must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding!r}')
                parts.setdefault(stamp, {})['depth'] = depth_to_metres(conv.image_to_numpy(msg))
        except conv.ConversionError as err:
            reader.problems.append(f'{m.topic} at {stamp}: {err}; skipped')
    for stamp in sorted(parts):
        frame = complete(stamp)
        if frame is not None:
            yield frame


_WORKER: dict[str, Any] = {}    # the prior of an object worker process (`workers` > 1)


def _worker_start(prior_path: str, device: str, threads: int) -> None:
    import torch
    torch.set_num_threads(threads)
    _WORKER['prior'] = ShapePrior.load(prior_path, device=device)


def _worker_object(optim: OptimConfig, obj: ObjectInput, views: ViewMemory,
                   scene: Scene) -> tuple[ObjectOutcome, ObjectEstimate | None]:
    """One object's fused -> sparse -> dense in a worker process: its outcome and final estimate."""
    reconstructor = ObjectReconstructor(_WORKER['prior'], optim)
    outcome = reconstructor.reconstruct(obj, views, scene)
    return outcome, reconstructor.estimates.get(obj.object_id)


def _object_pool(workers: int, prior: ShapePrior, device: str):
    """`workers` fresh (spawned) processes, each with the prior loaded and threads / workers torch threads."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    import torch
    threads = max(1, torch.get_num_threads() // workers)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context('spawn'), initializer=_worker_start,
                               initargs=(str(prior.path), device, threads))
    for _ in range(workers):      # processes start on demand: ask for all of them now
        pool.submit(int)
    return pool


def reconstruct(bag: str | os.PathLike, config: PipelineConfig | None = None,
                progress: Callable[[str], None] | None = None, prior: ShapePrior | None = None,
                on_stage: Callable[[StageOutcome], None] | None = None, workers: int = 1) -> ObjectMap:
    """Reconstruct every object of a contract bag (see the module docstring). progress: called with one line
    per phase and per object stage; prior: an already loaded prior (default: `config.optim.prior`); on_stage:
    called with each object stage's `StageOutcome` as it ends (stage, reason, seconds, iterations, views; with
    workers > 1 when the object's last stage has ended). workers: processes that refine objects at the same
    time (1: this process, one object after the other); results depend on it through each worker's thread count
    only (floating-point order), and are the same from run to run for a given value.
    Raises preflight.BagRefused when the bag cannot give objects (checked before any work), PipelineError
    when no frame is complete."""
    if int(workers) < 1:
        raise ValueError(f'workers must be >= 1, got {workers}')
    config = config or PipelineConfig()
    say = progress or (lambda line: None)
    reader = BagReader(bag)
    backend = {spec.name: spec.default for spec in DETECTION_PARAMS} | config.detection
    check_bag(reader, backend['backend'])
    filt = filter_config(backend)
    detector = make_detector(backend)
    if prior is None:
        prior = ShapePrior.load(config.optim.prior, device=config.optim.device)
    # started now, so that the workers' start-up (imports, prior) overlaps the association and the encoding
    pool = _object_pool(int(workers), prior, config.optim.device) if int(workers) > 1 else None
    try:
        return _reconstruct(reader, config, prior, detector, filt, say, on_stage, pool)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)


def _reconstruct(reader: BagReader, config: PipelineConfig, prior: ShapePrior, detector, filt, say, on_stage,
                 pool) -> ObjectMap:
    seconds: dict[str, float] = {}

    # pass 1: detection + association of every frame, then every object's box fitted to all its detections
    t0 = time.perf_counter()
    associator = FrameAssociator(config.association, config.evidence)
    kept_instances: dict[int, bytes] = {}   # stamp -> filtered instance image (zlib), reused by pass 2
    shapes: dict[int, tuple[int, int]] = {}
    frames = 0
    for frame in bag_frames(reader, need_instances=detector is None, with_rgb=detector is not None):
        raw = detector.detect(frame.rgb) if detector is not None else frame.instances
        if (frame.size[1], frame.size[0]) != raw.shape:
            reader.problems.append(f'frame {frame.stamp}: instances {raw.shape[::-1]} do not match camera_info '
                                   f'{frame.size}; skipped')
            continue
        instances, _ = filter_instances(raw, filt)
        depth = frame.depth_m if frame.depth_m is not None and frame.depth_m.shape == instances.shape else None
        associator.add(frame.stamp, frame.K, frame.T_world_camera, frame.size, instances, depth, frame.landmarks)
        kept_instances[frame.stamp] = zlib.compress(instances.tobytes(), 1)
        shapes[frame.stamp] = instances.shape
        frames += 1
    if frames == 0:
        raise PipelineError(f'{reader.path}: no complete frame (image, pose, camera info'
                            f'{", instances" if detector is None else ""} of one stamp)')
    assoc = associator.associator
    assoc.settle()       # the end of the input: final pass, confirmation and boxes of the whole sequence
    tracks = {t.object_id: (category_by_id(t.coco_id).name, t.box) for t in assoc.confirmed_tracks()
              if t.box is not None}
    seconds['association'] = time.perf_counter() - t0
    say(f'association: {frames} frames, {len(tracks)} objects ({seconds["association"]:.1f} s)')

    # pass 2: codes and views under the final ids
    t0 = time.perf_counter()
    encoder = CodeEncoder(prior, config.shape)
    views = ViewMemory(config.optim)
    landmarks = None
    associations: dict[int, np.ndarray] = {}
    for frame in bag_frames(reader, need_instances=False):
        landmarks = frame.landmarks if frame.landmarks is not None else landmarks
        if frame.stamp not in kept_instances:
            continue
        labels = np.frombuffer(zlib.decompress(kept_instances.pop(frame.stamp)), np.uint16).reshape(shapes[frame.stamp])
        if frame.rgb.shape[:2] != labels.shape:
            reader.problems.append(f'frame {frame.stamp}: image {frame.rgb.shape[1::-1]} does not match the '
                                   f'instances {labels.shape[::-1]}; not encoded')
            continue
        rows = assoc.frame_table(frame.stamp)
        associations[frame.stamp] = rows
        encoder.encode_frame(frame.stamp, frame.rgb, labels, rows)
        depth = frame.depth_m if frame.depth_m is not None and frame.depth_m.shape == labels.shape else None
        views.add_frame(frame.stamp, frame.K, frame.T_world_camera, labels, rows, frame.rgb, depth)
    codes = {int(r['object_id']): (int(r['category']), int(r['num_views']), np.asarray(r['code'], np.float32))
             for r in encoder.fused_codes()}
    seconds['encoding'] = time.perf_counter() - t0
    say(f'encoding: {sum(c[1] for c in codes.values())} crops of {len(codes)} objects ({seconds["encoding"]:.1f} s)')

    # per object: fused -> sparse -> dense
    t0 = time.perf_counter()
    reconstructor = ObjectReconstructor(prior, config.optim)
    scene = Scene(landmarks, tracks)
    outcomes: dict[int, ObjectOutcome] = {}
    todo = [oid for oid in sorted(tracks) if oid in codes and codes[oid][1] >= config.optim.min_views]

    def stage_ended(stage: StageOutcome) -> None:
        name = tracks[stage.object_id][0]
        say(f'object {stage.object_id} ({name}): {stage.stage} {stage.seconds:.1f} s, {stage.reason.text}'
            + (f' ({stage.detail})' if stage.detail else ''))
        if on_stage is not None:
            on_stage(stage)

    inputs = {oid: ObjectInput(oid, tracks[oid][0], codes[oid][0], tracks[oid][1], codes[oid][2], codes[oid][1])
              for oid in todo}
    if pool is None:
        for oid in todo:
            outcomes[oid] = reconstructor.reconstruct(inputs[oid], views, scene, on_stage=stage_ended)
        estimates = dict(reconstructor.estimates)
    else:
        from concurrent.futures import as_completed
        futures = {pool.submit(_worker_object, config.optim, inputs[oid], views.of_object(oid), scene): oid
                   for oid in todo}
        finals: dict[int, ObjectEstimate | None] = {}
        for future in as_completed(futures):
            oid = futures[future]
            outcomes[oid], finals[oid] = future.result()
            for stage in outcomes[oid].stages:
                stage_ended(stage)
        outcomes = {oid: outcomes[oid] for oid in todo}
        estimates = {oid: finals[oid] for oid in todo if finals[oid] is not None}
    for oid, outcome in outcomes.items():
        if outcome.error:
            reader.problems.append(f'object {oid}: {outcome.error}')
            say(f'object {oid}: {outcome.error}')
    seconds['optimisation'] = time.perf_counter() - t0
    return ObjectMap(estimates, outcomes, config.world_frame, frames,
                     topics.GROUND_TRUTH in reader.topics(), list(reader.problems), seconds, tracks, associations)
