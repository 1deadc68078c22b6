"""Per-object reconstruction, coarse to fine (paper Sec. 5.3), without ROS: the stage policy that the optimiser
node schedules and the offline pipeline (`frodo reconstruct`) runs synchronously.

For one object (its association box, fused code and stored views) `ObjectReconstructor.reconstruct` runs
- fused: the mesh decoded from the fused code (cached while the code moves by less than
  `code_change_tolerance`) placed by its box (`core.fused_estimate`);
- sparse: yaw search + code/pose optimisation on silhouettes and landmarks (`sparse.refine`);
- dense: code + 7-DoF pose on the SDF decoder (`dense.refine_dense_starts`), deferred while other objects wait
  unless the object's views grew by `dense_rerun_growth` since its last dense run;
and keeps the current estimate of every object. Each stage ends with a `StageOutcome` whose `reason` is a
`StageReason` value (never text to parse); a stage that cannot improve keeps what was there, with its reason.
Every estimate carries its data time (`ObjectEstimate.stamp_ns`): the newest of the input's stamp and the
stamps of the stored views of the object, i.e. the newest frame it was made from, so that outputs keep the
bag's (the sensor's) time.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from frodo_common.categories import category_by_id
from frodo_common.geometry import Box3D
from frodo_optim import support
from frodo_optim.config import OptimConfig
from frodo_optim.core import ObjectEstimate, fused_estimate, world_box
from frodo_optim.dense import DenseResult, DenseStop, refine_dense_starts
from frodo_optim.photometric import ViewBatch
from frodo_optim.sparse import SparseResult, SparseStatus, refine, select_views, with_depth_points
from frodo_optim.states import StageReason
from frodo_optim.views import ViewMemory



@dataclass
class ObjectInput:
    """What the front end says of one object: its track box and fused code (Sec. 5.1-5.2)."""

    object_id: int
    class_name: str          # the track's class (used when `category` is no known COCO id)
    category: int            # COCO id of the fused code's detections
    box: Box3D
    code: np.ndarray         # (C,) fused code
    num_views: int           # detections the fused code came from
    stamp_ns: int = 0        # newest frame stamp (ns) of the box and code (0: unknown; the stored views say)


@dataclass
class Scene:
    """What the stages need of the rest of the map: landmarks (N, 3) or None, and the other objects' tracks
    {id: (class name, box)} (floor estimate, neighbour boxes for the landmark selection)."""

    slam_points: np.ndarray | None = None
    tracks: dict[int, tuple[str, Box3D]] = field(default_factory=dict)


@dataclass
class StageOutcome:
    """How one stage of one object ended. estimate: the object's estimate after it (None: the object has none);
    detail: the stage's own words (energies, iterations, times) for diagnostics."""

    object_id: int
    stage: str                       # 'fused' | 'sparse' | 'dense': the stage that ran
    reason: StageReason
    estimate: ObjectEstimate | None
    detail: str = ''
    seconds: float = 0.0
    published: bool = True           # the estimate changed (a listener should publish the map)
    iterations: int = 0              # optimiser iterations of every run/start of the stage (sparse, dense)
    views: int = 0                   # views the stage used
    energies: dict[str, float] = field(default_factory=dict)   # sparse/dense: total energy 'initial', 'final'


@dataclass
class ObjectOutcome:
    """Every stage that ran for one object in one `reconstruct` call; `error`: why it has no estimate at all."""

    object_id: int
    stages: list[StageOutcome] = field(default_factory=list)
    dense_deferred: bool = False
    error: str = ''

    @property
    def final(self) -> StageOutcome | None:
        return self.stages[-1] if self.stages else None


@dataclass
class StageStep:
    """What `ObjectReconstructor.run_stage` did: the stage's outcome (None: it did not run), the stage that may
    follow (None: the object is done for now), why the object has no estimate (`error`), that its dense
    stage waits until no other object does (`deferred`), or that its sparse stage stopped for waiting work
    (`yielded`: nothing changed, run it again)."""

    outcome: StageOutcome | None
    next: str | None
    error: str = ''
    deferred: bool = False
    yielded: bool = False


class ObjectReconstructor:
    """The object map of the optimiser: `estimates` {id: ObjectEstimate}, refined object by object."""

    def __init__(self, prior, config: OptimConfig | None = None):
        self.prior = prior
        self.config = config or OptimConfig()
        self.estimates: dict[int, ObjectEstimate] = {}
        self.mesh_cache: dict[int, tuple[np.ndarray, object]] = {}   # id -> (code, normalised mesh)
        self.dense_views_used: dict[int, int] = {}                   # id -> num_views at its last dense run
        self.sparse_results: dict[int, tuple[ObjectEstimate, SparseResult]] = {}   # id -> its last sparse stage

    def forget(self, object_id: int) -> bool:
        """Drop an object (its track is gone); True when it had an estimate."""
        self.mesh_cache.pop(object_id, None)
        self.dense_views_used.pop(object_id, None)
        self.sparse_results.pop(object_id, None)
        return self.estimates.pop(object_id, None) is not None

    def dense_due(self, object_id: int, num_views: int, others_waiting: bool) -> bool:
        """Whether the dense stage runs now: always for an object never run densely or when nobody else waits,
        otherwise only once its views grew by `dense_rerun_growth` (breadth over depth while a bag plays)."""
        used = self.dense_views_used.get(object_id)
        return (used is None or not others_waiting
                or num_views >= self.config.dense_rerun_growth * used)

    def reconstruct(self, obj: ObjectInput, views: ViewMemory, scene: Scene, *, others_waiting: bool = False,
                    should_stop: Callable[[], bool] | None = None,
                    on_stage: Callable[[StageOutcome], None] | None = None) -> ObjectOutcome:
        """Fused, then sparse, then dense for one object (`run_stage` in turn); `on_stage` is called after each
        stage (the node publishes the map there). A refined object keeps its last refinement until a new one
        replaces it."""
        outcome = ObjectOutcome(obj.object_id)

        def emit(stage: StageOutcome) -> None:
            outcome.stages.append(stage)
            if on_stage is not None:
                on_stage(stage)

        stage: str | None = 'fused'
        while stage is not None:
            step = self.run_stage(obj, stage, views, scene, others_waiting=others_waiting, should_stop=should_stop,
                                  on_stage=emit)
            if step.error:
                outcome.error = step.error
                break
            outcome.dense_deferred = step.deferred
            stage = step.next
        return outcome

    def run_stage(self, obj: ObjectInput, stage: str, views: ViewMemory, scene: Scene, *,
                  others_waiting: bool = False, should_stop: Callable[[], bool] | None = None,
                  on_stage: Callable[[StageOutcome], None] | None = None) -> 'StageStep':
        """One stage of one object, for a scheduler that interleaves objects (breadth first): 'fused' places the
        decoded mesh, 'sparse' refines from the fused placement, 'dense' from the object's last sparse result
        (kept from its sparse stage). `StageStep.next` says which stage may follow. A dense stage that is not
        due (`dense_due`) while others wait does not run (`deferred`). should_stop: polled by the sparse stage
        every iteration of its runs (it then ends `yielded`, nothing kept) and by the dense stage every iteration (it keeps
        its best state so far)."""
        cfg = self.config
        oid = obj.object_id
        emit = on_stage or (lambda outcome: None)
        stamp = max(int(obj.stamp_ns), views.newest_stamp(oid))
        if stage == 'dense':
            stored = self.sparse_results.get(oid)
            if stored is None or not cfg.dense_on:
                return StageStep(None, None)
            if not self.dense_due(oid, obj.num_views, others_waiting):
                return StageStep(None, None, deferred=True)
            sparse_estimate, result = stored
            floor = support.scene_floor(scene.tracks, scene.slam_points)
            outcome = self._dense(obj, sparse_estimate, result, views, scene, floor, should_stop, stamp)
            emit(outcome)
            return StageStep(outcome, None)
        fused = self._fused(obj, stamp)
        if fused is None:
            return StageStep(None, None, error='decoded shape has no surface (code far from the prior?)')
        if stage == 'fused':
            previous = self.estimates.get(oid)
            replace_previous = previous is None or previous.stage == 'fused' or not cfg.sparse_enabled
            if replace_previous:
                self.estimates[oid] = fused
            outcome = StageOutcome(oid, 'fused', StageReason(fused.stage_reason), self.estimates[oid],
                                   seconds=fused.timings['fused_s'], published=replace_previous)
            emit(outcome)
            return StageStep(outcome, 'sparse' if cfg.sparse_enabled else None)
        if stage != 'sparse':
            raise ValueError(f"unknown stage {stage!r}: 'fused', 'sparse' or 'dense'")
        floor = support.scene_floor(scene.tracks, scene.slam_points)
        outcome, result = self._sparse(obj, fused, views, scene, floor, stamp, should_stop)
        if result is not None and result.status is SparseStatus.INTERRUPTED:
            return StageStep(None, None, yielded=True)
        if result is not None:
            self.sparse_results[oid] = (outcome.estimate, result)
        emit(outcome)
        return StageStep(outcome, 'dense' if result is not None and cfg.dense_on else None)

    # ------------------------------------------------------------ stages
    def _fused(self, obj: ObjectInput, stamp: int) -> ObjectEstimate | None:
        start = time.perf_counter()
        cached = self.mesh_cache.get(obj.object_id)
        tol = self.config.code_change_tolerance
        if cached is None or np.linalg.norm(obj.code - cached[0]) > tol * max(np.linalg.norm(cached[0]), 1e-6):
            # the object's first mesh, shown until its sparse stage ends: coarser, so that it comes sooner
            resolution = min(self.config.fused_mesh_resolution, self.config.mesh_resolution)
            mesh = self.prior.mesh(obj.code, resolution=resolution)
            if mesh is None or len(mesh.faces) == 0:
                return None
            self.mesh_cache[obj.object_id] = (obj.code, mesh)
        mesh = self.mesh_cache[obj.object_id][1]
        known = category_by_id(obj.category)
        estimate = fused_estimate(obj.object_id, known.name if known else obj.class_name, obj.category, obj.code,
                                  obj.num_views, mesh, obj.box, stamp)
        estimate.timings['fused_s'] = time.perf_counter() - start
        estimate.stage_reason = StageReason.IN_PROGRESS if self.config.sparse_enabled else StageReason.SPARSE_DISABLED
        return estimate

    def _sparse(self, obj: ObjectInput, fused: ObjectEstimate, views: ViewMemory, scene: Scene, floor: float | None,
                stamp: int, should_stop: Callable[[], bool] | None = None) -> tuple[StageOutcome | None, SparseResult | None]:
        """The sparse stage; on failure the fused result stays (replacing an older refinement), with the reason;
        interrupted by should_stop: (None, the interrupted result), nothing changed."""
        cfg = self.config
        oid = obj.object_id
        photometric = None
        if cfg.sparse.w_photometric > 0:
            colour = select_views(views.dense_views(oid), cfg.sparse.max_views)
            photometric = ViewBatch(colour) if colour else None   # sparse runs on CPU
        t0 = time.perf_counter()
        landmarks = with_depth_points(scene.slam_points, [v.depth_points for v in views.dense_views(oid)],
                                      cfg.sparse.depth_points)
        result = refine(self.prior, obj.code, obj.box, views.sparse_views(oid), landmarks, cfg.sparse,
                        photometric=photometric, floor_height=floor,
                        height_range=support.class_height_range(fused.class_name), code_class=fused.class_name,
                        neighbour_boxes=[b for other, (_, b) in scene.tracks.items() if other != oid],
                        should_stop=should_stop, facing=self._facing(obj, fused.class_name, scene))
        if result.status is SparseStatus.INTERRUPTED:
            return None, result
        seconds = time.perf_counter() - t0
        mesh = self.prior.mesh(result.code, resolution=cfg.mesh_resolution) if result.ok else None
        if mesh is None or len(mesh.faces) == 0:
            detail = result.reason if not result.ok else 'refined code decodes to no surface; fused result kept'
            fused.stage_reason = StageReason.SPARSE_FAILED
            current = self.estimates.get(oid)
            if current is None or current.stage != 'fused':
                self.estimates[oid] = fused
            else:
                current.stage_reason = StageReason.SPARSE_FAILED
            return StageOutcome(oid, 'sparse', StageReason.SPARSE_FAILED, self.estimates[oid], detail, seconds), None
        mesh_world = mesh.copy()
        mesh_world.apply_transform(result.T_world_object)
        reason = StageReason.IN_PROGRESS if cfg.dense_on else StageReason.DENSE_DISABLED
        estimate = ObjectEstimate(oid, fused.class_name, fused.category, result.code, result.T_world_object,
                                  result.scale, world_box(mesh, result.T_world_object, result.yaw), fused.num_views,
                                  'sparse', mesh_world, dict(fused.timings, sparse_s=seconds), reason, stamp)
        self.estimates[oid] = estimate
        e0, e1 = result.initial_energies.get('total', np.nan), result.energies.get('total', np.nan)
        detail = (f'{result.views} views, {result.iterations} it, E {e0:.3f}->{e1:.3f}, {result.seconds:.2f}s, '
                  f'start: {result.placement}')
        return StageOutcome(oid, 'sparse', reason, estimate, detail, seconds,
                            energies=_energies(result.initial_energies, result.energies),
                            iterations=result.total_iterations, views=result.views), result

    def _facing(self, obj: ObjectInput, class_name: str, scene: Scene) -> np.ndarray | None:
        """The direction the object should face (E_facing, `support.facing_direction`): towards the table its
        association box stands at, if any."""
        others = [track for other, track in scene.tracks.items() if other != obj.object_id]
        return support.facing_direction(class_name, obj.box, others, self.config.facing_max_gap)

    def _dense(self, obj: ObjectInput, sparse: ObjectEstimate, sparse_result: SparseResult, views: ViewMemory,
               scene: Scene, floor: float | None, should_stop: Callable[[], bool] | None, stamp: int) -> StageOutcome:
        """The dense stage after a successful sparse stage: the dense estimate, or the sparse one with the reason."""
        oid = obj.object_id
        self.dense_views_used[oid] = obj.num_views
        slam, box = scene.slam_points, obj.box
        if sparse_result.landmarks is not None:
            slam, box = sparse_result.landmarks, None     # already the object's: no box selection
        t0 = time.perf_counter()
        result, _ = refine_dense_starts(self.prior, sparse.code, sparse.T_world_object, views.dense_views(oid), slam,
                                        box, self.config.dense, should_stop=should_stop,
                                        floor_height=floor, height_range=support.class_height_range(sparse.class_name),
                                        alternatives=sparse_result.alternatives, max_starts=self.config.dense_starts,
                                        facing=self._facing(obj, sparse.class_name, scene))
        seconds = time.perf_counter() - t0
        detail = (f'{result.views} views, {result.iterations} it, {result.seconds:.2f}s '
                  f'({result.seconds_per_iteration:.2f}s/it): {result.reason}')
        mesh = self.prior.mesh(result.code, resolution=self.config.mesh_resolution) if result.improved else None
        reason = dense_reason(result, has_surface=mesh is not None and len(mesh.faces) > 0)
        energies = _energies(result.initial_energies, result.energies)
        if mesh is None or len(mesh.faces) == 0:
            if result.improved:
                detail += '; dense code decodes to no surface, sparse result kept'
            if self.estimates.get(oid) is sparse:
                sparse.stage_reason = reason
                sparse.timings['dense_s'] = seconds
            return StageOutcome(oid, 'dense', reason, self.estimates.get(oid), detail, seconds, energies=energies,
                                iterations=result.total_iterations, views=result.views)
        mesh_world = mesh.copy()
        mesh_world.apply_transform(result.T_world_object)
        estimate = ObjectEstimate(oid, sparse.class_name, sparse.category, result.code, result.T_world_object,
                                  result.scale, world_box(mesh, result.T_world_object, result.yaw), sparse.num_views,
                                  'dense', mesh_world, dict(sparse.timings, dense_s=seconds), reason, stamp)
        self.estimates[oid] = estimate
        return StageOutcome(oid, 'dense', reason, estimate, detail, seconds, energies=energies,
                            iterations=result.total_iterations, views=result.views)


def _energies(initial: dict[str, float], final: dict[str, float]) -> dict[str, float]:
    """The total energy before and after a stage's optimisation ('initial', 'final'; finite values only)."""
    out = {'initial': initial.get('total', np.nan), 'final': final.get('total', np.nan)}
    return {k: float(v) for k, v in out.items() if v is not None and np.isfinite(v)}


def dense_reason(result: DenseResult, has_surface: bool) -> StageReason:
    """The stage reason of a dense run: accepted (improved, with a surface) or why the sparse result stays."""
    if result.improved and has_surface:
        return {DenseStop.TIME_LIMIT: StageReason.DENSE_TIME_LIMIT,
                DenseStop.INTERRUPTED: StageReason.DENSE_INTERRUPTED}.get(result.stop, StageReason.ALL_STAGES_DONE)
    if result.improved or result.stop in (DenseStop.NO_VIEWS, DenseStop.INVALID_INPUT, DenseStop.NO_SURFACE,
                                          DenseStop.NON_FINITE_ENERGY):
        return StageReason.DENSE_FAILED
    if result.stop is DenseStop.INTERRUPTED:
        return StageReason.DENSE_INTERRUPTED
    return StageReason.DENSE_NOT_BETTER
