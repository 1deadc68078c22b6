"""Per-object stage policy without ROS (paper Sec. 5.3, fused -> sparse -> dense): every stage ends with a typed
reason, a stage that cannot improve keeps what was there, and the two outcomes free-text matching got wrong
(a dense run interrupted at shutdown; a sparse result that decodes to no surface) have reasons of their own."""
from dataclasses import replace

import numpy as np
import pytest

from frodo_common.geometry import Box3D
from frodo_common.schemas import ASSOCIATION_DTYPE
from frodo_optim.config import OptimConfig, PARAMS, optim_config
from frodo_optim.dense import DenseResult, DenseStop
from frodo_optim.reconstructor import ObjectInput, ObjectReconstructor, Scene, dense_reason
from frodo_optim.states import STAGE_REASONS, StageReason
from frodo_optim.views import ViewMemory
from frodo_shape.prior import ShapePrior

CHAIR = 62


@pytest.fixture(scope='module')
def prior():
    return ShapePrior.load('furniture', device='cpu')


def fast_config(**overrides) -> OptimConfig:
    """A few iterations of each stage: the policy, not the accuracy, is under test."""
    cfg = OptimConfig(prior='furniture', device='cpu', mesh_resolution=32, dense_starts=1)
    cfg = replace(cfg, sparse=replace(cfg.sparse, iterations=3, yaw_candidates=4, code_restarts=0,
                                      placement_search=False),
                  dense=replace(cfg.dense, iterations=2, grid_resolution=16, rays_per_view=64, max_views=4))
    return replace(cfg, **overrides)


def memory_of(frames, K, config: OptimConfig) -> ViewMemory:
    views = ViewMemory(config)
    for stamp, rgb, labels, T in frames:
        ids = [int(v) for v in np.unique(labels) if v]
        rows = np.zeros(len(ids), dtype=ASSOCIATION_DTYPE)
        rows['label'], rows['object_id'], rows['kept'] = ids, ids, 1
        views.add_frame(stamp, K, T, labels, rows, rgb)
    return views


def chair_input(two_chairs, oid: int = 1) -> ObjectInput:
    _, _, boxes, codes = two_chairs
    return ObjectInput(oid, 'chair', CHAIR, boxes[oid], codes[oid], 6)


class RecordingPrior:
    """The real prior, recording the resolution of every mesh it makes."""

    def __init__(self, prior):
        self.prior, self.resolutions = prior, []

    def __getattr__(self, name):
        return getattr(self.prior, name)

    def mesh(self, code, resolution=64):
        self.resolutions.append(resolution)
        return self.prior.mesh(code, resolution=resolution)


class NoSurfaceAfterFirstMesh(RecordingPrior):
    """The real prior, except that every mesh after the first decodes to nothing (a refined code far from the
    prior): the fused stage gets its mesh, the sparse result none."""

    def mesh(self, code, resolution=64):
        if self.resolutions:
            self.resolutions.append(resolution)
            return None
        return super().mesh(code, resolution)


def test_all_three_stages_run_and_each_ends_with_a_reason(prior, two_chairs):
    K, frames, _, _ = two_chairs
    cfg = fast_config()
    rec = ObjectReconstructor(prior, cfg)
    seen = []
    out = rec.reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg), Scene(), on_stage=seen.append)
    assert [s.stage for s in out.stages] == ['fused', 'sparse', 'dense'] and seen == out.stages
    assert out.stages[0].reason is StageReason.IN_PROGRESS and out.stages[1].reason is StageReason.IN_PROGRESS
    # the sparse stage names the start that won (the input box, a placement hypothesis, a training code)
    assert out.stages[1].detail.endswith(f'start: {rec.sparse_results[1][1].placement}')
    assert rec.sparse_results[1][1].placement
    final = rec.estimates[1]
    assert out.final.reason in (StageReason.ALL_STAGES_DONE, StageReason.DENSE_NOT_BETTER)
    assert final.stage_reason == out.final.reason and final.stage == ('dense' if out.final.reason
                                                                     is StageReason.ALL_STAGES_DONE else 'sparse')
    assert {'fused_s', 'sparse_s', 'dense_s'} <= set(final.timings)


def test_a_chair_next_to_a_table_of_the_scene_is_given_the_facing_prior(prior, two_chairs):
    """The scene's tracks reach the stages: a chair whose box stands at a table's gets E_facing (support.py), one
    with no table near it does not."""
    K, frames, boxes, _ = two_chairs
    center, size, yaw = boxes[1]
    table = Box3D(np.asarray(center) + [0.5 * size[0] + 0.45, 0.0, 0.0], [0.8, 1.4, 0.75], 0.0)
    cfg = fast_config(dense_enabled=False)
    energies = []
    for tracks in ({7: ('dining table', table)}, {7: ('chair', table)}, {}):
        rec = ObjectReconstructor(prior, cfg)
        rec.reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg), Scene(tracks=tracks))
        energies.append(rec.sparse_results[1][1].energies)
    assert 'facing' in energies[0] and 'facing' not in energies[1] and 'facing' not in energies[2]


def test_the_fused_mesh_is_coarser_and_the_refined_ones_at_mesh_resolution(prior, two_chairs):
    """An object's first mesh comes at fused_mesh_resolution (sooner), the sparse and dense ones at
    mesh_resolution; a fused resolution above mesh_resolution is capped to it."""
    K, frames, _, _ = two_chairs
    for fused, expected in ((16, 16), (64, 32)):
        cfg = fast_config(fused_mesh_resolution=fused)
        counting = RecordingPrior(prior)
        out = ObjectReconstructor(counting, cfg).reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg),
                                                             Scene())
        assert [s.stage for s in out.stages] == ['fused', 'sparse', 'dense']
        assert counting.resolutions[0] == expected and set(counting.resolutions[1:]) == {cfg.mesh_resolution}


def test_a_dense_run_interrupted_at_shutdown_says_so(prior, two_chairs):
    K, frames, _, _ = two_chairs
    cfg = fast_config()
    rec = ObjectReconstructor(prior, cfg)
    done = []          # the stop comes once the sparse stage has ended
    out = rec.reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg), Scene(),
                          should_stop=lambda: 'sparse' in done, on_stage=lambda stage: done.append(stage.stage))
    assert out.final.stage == 'dense' and out.final.reason is StageReason.DENSE_INTERRUPTED
    assert rec.estimates[1].stage == 'sparse' and rec.estimates[1].stage_reason == StageReason.DENSE_INTERRUPTED


def test_a_sparse_run_asked_to_stop_yields_and_changes_nothing(prior, two_chairs):
    """A sparse stage asked to stop (a node with a new object's first mesh waiting) ends `yielded`:
    no outcome, no next stage, the fused estimate and no sparse result kept; run again, it completes."""
    K, frames, _, _ = two_chairs
    cfg = fast_config()
    rec = ObjectReconstructor(prior, cfg)
    views, obj = memory_of(frames, K, cfg), chair_input(two_chairs)
    rec.run_stage(obj, 'fused', views, Scene())
    fused = rec.estimates[1]
    step = rec.run_stage(obj, 'sparse', views, Scene(), should_stop=lambda: True)
    assert step.yielded and step.outcome is None and step.next is None
    assert rec.estimates[1] is fused and 1 not in rec.sparse_results
    step = rec.run_stage(obj, 'sparse', views, Scene(), should_stop=lambda: False)
    assert not step.yielded and step.next == 'dense' and rec.estimates[1].stage == 'sparse'


def test_a_sparse_result_without_surface_keeps_the_fused_estimate_as_failed(prior, two_chairs):
    K, frames, _, _ = two_chairs
    cfg = fast_config()
    rec = ObjectReconstructor(NoSurfaceAfterFirstMesh(prior), cfg)
    out = rec.reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg), Scene())
    assert [s.stage for s in out.stages] == ['fused', 'sparse']
    assert out.final.reason is StageReason.SPARSE_FAILED and 'no surface' in out.final.detail
    assert rec.estimates[1].stage == 'fused' and rec.estimates[1].stage_reason == StageReason.SPARSE_FAILED


def test_no_views_fail_the_sparse_stage_and_disabled_stages_are_named(prior, two_chairs):
    K, frames, _, _ = two_chairs
    rec = ObjectReconstructor(prior, fast_config())
    out = rec.reconstruct(chair_input(two_chairs), ViewMemory(fast_config()), Scene())
    assert out.final.reason is StageReason.SPARSE_FAILED and 'no usable views' in out.final.detail
    assert ObjectReconstructor(prior, fast_config(sparse_enabled=False)).reconstruct(
        chair_input(two_chairs), ViewMemory(fast_config()), Scene()).final.reason is StageReason.SPARSE_DISABLED
    cfg = fast_config(dense_enabled=False)
    out = ObjectReconstructor(prior, cfg).reconstruct(chair_input(two_chairs), memory_of(frames, K, cfg), Scene())
    assert [s.stage for s in out.stages] == ['fused', 'sparse'] and out.final.reason is StageReason.DENSE_DISABLED


def test_a_code_without_surface_gives_no_estimate_and_says_why(prior, two_chairs):
    obj = replace(chair_input(two_chairs), code=np.full(64, 50.0, np.float32))
    rec = ObjectReconstructor(prior, fast_config())
    out = rec.reconstruct(obj, ViewMemory(fast_config()), Scene())
    assert out.stages == [] and 'no surface' in out.error and 1 not in rec.estimates


def test_dense_reruns_wait_for_enough_new_views_while_others_wait(prior):
    rec = ObjectReconstructor(prior, fast_config(dense_rerun_growth=1.5))
    assert rec.dense_due(7, 10, others_waiting=True)            # never run densely: now
    rec.dense_views_used[7] = 10
    assert not rec.dense_due(7, 14, others_waiting=True) and rec.dense_due(7, 15, others_waiting=True)
    assert rec.dense_due(7, 11, others_waiting=False)           # nobody waits: catch up


@pytest.mark.parametrize('improved, stop, surface, expected', [
    (True, DenseStop.COMPLETED, True, StageReason.ALL_STAGES_DONE),
    (True, DenseStop.TIME_LIMIT, True, StageReason.DENSE_TIME_LIMIT),
    (True, DenseStop.INTERRUPTED, True, StageReason.DENSE_INTERRUPTED),
    (False, DenseStop.INTERRUPTED, False, StageReason.DENSE_INTERRUPTED),
    (False, DenseStop.COMPLETED, False, StageReason.DENSE_NOT_BETTER),
    (False, DenseStop.TIME_LIMIT, False, StageReason.DENSE_NOT_BETTER),
    (False, DenseStop.NO_VIEWS, False, StageReason.DENSE_FAILED),
    (False, DenseStop.NON_FINITE_ENERGY, False, StageReason.DENSE_FAILED),
    (True, DenseStop.COMPLETED, False, StageReason.DENSE_FAILED),     # improved, but its code has no surface
])
def test_dense_outcomes_map_to_stage_reasons(improved, stop, surface, expected):
    result = DenseResult(np.zeros(64, np.float32), np.eye(4), 1.0, np.eye(3), np.zeros(3), improved, 'x', stop)
    assert dense_reason(result, surface) is expected


def test_stage_reason_values_and_texts_are_stable():
    # the value travels in /frodo/object_states and the text in objects.json: append only
    assert STAGE_REASONS[:8] == ('in progress', 'all stages done', 'sparse stage disabled', 'sparse stage failed',
                                 'dense stage disabled', 'dense not better than sparse', 'dense stage failed',
                                 'dense time limit')
    assert StageReason.from_text('dense interrupted') is StageReason.DENSE_INTERRUPTED


def test_node_parameters_come_from_the_config_dataclasses():
    defaults = {spec.name: spec.default for spec in PARAMS}
    cfg = OptimConfig()
    assert defaults['sparse_iterations'] == cfg.sparse.iterations and defaults['dense_views'] == cfg.dense.max_views
    changed = optim_config({'support_w_floor': 0.2, 'dense_starts': 1})
    assert changed.sparse.w_floor == changed.dense.w_floor == 0.2 and changed.dense_starts == 1
    with pytest.raises(ValueError, match='unknown optimiser parameter'):
        optim_config({'sparse_iteration': 3})
