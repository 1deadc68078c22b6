"""The Rerun recording (frodo_bringup.recording), pure and deterministic: an offline recording of the demo bag with
a hand-built object map is read back (rerun.chunk.RrdReader) and has the entity layout, one data-time range for
images and objects (no wall-clock timeline), the detections' classes with label 0 as transparent background,
meshes coloured by stage and grey ground truth; a live-style sequence of maps clears objects that leave the map
and recolours a mesh whose stage changes."""
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import trimesh
from rerun.chunk import RrdReader

from frodo_bringup import recording as rec
from frodo_bringup.pipeline import ObjectMap, bag_frames
from frodo_common.bag import BagReader
from frodo_common.evaluation import load_ground_truth_bag
from frodo_common.schemas import ASSOCIATION_DTYPE
from frodo_optim.core import ObjectEstimate
from frodo_optim.reconstructor import ObjectOutcome, StageOutcome
from frodo_optim.states import StageReason

BAG = Path(__file__).resolve().parents[3] / 'bags' / 'demo_walk.mcap'
pytestmark = pytest.mark.skipif(not BAG.exists(), reason='demo bag missing')


def read(path):
    """{entity: [(is_static, record batch)]} of a .rrd, and its blueprint stores."""
    reader = RrdReader(path)
    chunks: dict[str, list] = {}
    for chunk in reader.stream():
        chunks.setdefault(chunk.entity_path, []).append((chunk.is_static, chunk.to_record_batch()))
    return chunks, reader.blueprints()


def column(batches, name):
    """Every value of a column over an entity's chunks that have it (stamps as int64 ns)."""
    out = []
    for _, batch in batches:
        if name in batch.schema.names:
            col = batch.column(name)
            out += (col.cast(pa.int64()) if pa.types.is_timestamp(col.type) else col).to_pylist()
    return out


def component(batches, suffix):
    """Every row of the component column ending in `suffix` that sets it (each: the list of its instances)."""
    return [v for _, batch in batches for n in batch.schema.names if n.endswith(suffix)
            for v in batch.column(n).to_pylist() if v is not None]


def timed(batches, suffix):
    """(stamp, row) of every row that sets the component ending in `suffix`, in time and logging order."""
    out = []
    for _, batch in batches:
        for n in batch.schema.names:
            if n.endswith(suffix):
                stamps = batch.column('stamp').cast(pa.int64()).to_pylist()
                ids = batch.column('rerun.controls.RowId').to_pylist()
                out += [(t, i, v) for t, i, v in zip(stamps, ids, batch.column(n).to_pylist()) if v is not None]
    return [(t, v) for t, _, v in sorted(out, key=lambda e: (e[0], e[1]))]


def rgba(colour, alpha=1.0):
    r, g, b, a = rec._rgb255(colour, alpha)
    return (r << 24) | (g << 16) | (b << 8) | a


@pytest.fixture(scope='module')
def demo():
    frames = [(f.stamp, f.T_world_camera) for f in bag_frames(BagReader(BAG), need_instances=False, with_rgb=False)]
    gt = load_ground_truth_bag(BAG)
    return frames, gt


def estimate(oid, obj, stage, stamp):
    lo, hi = obj.mesh.bounds
    return ObjectEstimate(oid, obj.class_name, 62 if obj.class_name == 'chair' else 67, np.zeros(64, np.float32),
                          np.eye(4), 1.0, ((lo + hi) / 2, hi - lo, 0.0), 12, stage,
                          obj.mesh.copy().apply_translation([0.05, 0, 0]), {}, 0, stamp)


def test_offline_recording_of_the_demo_bag(tmp_path, demo):
    frames, gt = demo
    first, last = frames[0][0], frames[-1][0]
    chair, table = next(o for o in gt if o.class_name == 'chair'), next(o for o in gt if o.class_name == 'dining table')
    middle = frames[len(frames) // 2][0]
    estimates = {3: estimate(3, chair, 'dense', middle), 5: estimate(5, table, 'sparse', 0)}   # 0: stamp unknown
    outcomes = {3: ObjectOutcome(3, [
        StageOutcome(3, 'fused', StageReason.IN_PROGRESS, estimates[3]),
        StageOutcome(3, 'sparse', StageReason.IN_PROGRESS, estimates[3], energies={'initial': 2.0, 'final': 1.0}),
        StageOutcome(3, 'dense', StageReason.ALL_STAGES_DONE, estimates[3], energies={'initial': 0.8, 'final': 0.5})]),
        5: ObjectOutcome(5, [StageOutcome(5, 'sparse', StageReason.DENSE_DISABLED, estimates[5])])}
    rows = np.zeros(2, ASSOCIATION_DTYPE)
    rows[0] = (*chair.centroid, 62 * 256 + 1, 3, 1, (0, 0, 10, 10))
    rows[1] = (np.nan, np.nan, np.nan, 67 * 256 + 1, -1, 0, (0, 0, 5, 5))          # not associated: no segment
    box = estimates[3].box
    path = rec.write_recording(BAG, ObjectMap(estimates, outcomes), tmp_path / 'frodo.rrd',
                               tracks={3: ('chair', box)}, associations={middle: rows})
    assert path == tmp_path / 'frodo.rrd'
    chunks, blueprints = read(path)
    assert len(blueprints) == 1                                     # the layout travels with the file
    for entity in ('/world', '/world/camera', '/world/camera/image', '/world/camera/image/rgb',
                   '/world/camera/image/detections', '/world/slam_points', '/world/tracks', '/world/associations',
                   '/world/objects/chair_3', '/world/objects/chair_3/box', '/world/objects/dining_table_5',
                   '/plots/stage/chair_3', '/plots/views/chair_3', '/plots/energy/chair_3/sparse',
                   '/plots/energy/chair_3/dense'):
        assert entity in chunks, (entity, sorted(chunks))
    assert {f'/world/ground_truth/{rec.object_key(o.class_name, o.id)}' for o in gt} <= set(chunks)

    # One data-time range: images, detections and objects all on the bag's stamps; no wall-clock timeline.
    names = {n for batches in chunks.values() for _, b in batches for n in b.schema.names if not n.startswith('rerun.')
             and ':' not in n}
    assert names == {'stamp', 'frame'}
    image_stamps = column(chunks['/world/camera/image/rgb'], 'stamp')
    assert sorted(image_stamps) == [s for s, _ in frames]
    assert column(chunks['/world/camera/image/rgb'], 'frame') == list(range(1, len(frames) + 1))
    assert set(column(chunks['/world/camera/image/detections'], 'stamp')) <= set(image_stamps)
    assert column(chunks['/world/objects/chair_3'], 'stamp') == [middle]
    assert column(chunks['/world/objects/chair_3'], 'frame') == [len(frames) // 2 + 1]
    assert column(chunks['/world/objects/dining_table_5'], 'stamp') == [last]       # unknown: the last frame
    every = [s for batches in chunks.values() for s in column(batches, 'stamp')]
    assert first <= min(every) and max(every) <= last

    # Detections: COCO classes; label 0 is the background, transparent; classes named and coloured.
    context = component([b for b in chunks['/world/camera/image/detections'] if b[0]], 'AnnotationContext:context')[0][0]
    infos = {c['class_id']: c['class_description']['info'] for c in context}
    assert infos[0]['label'] == 'background' and infos[0]['color'] & 0xFF == 0
    assert infos[62]['label'] == 'chair' and infos[67]['label'] == 'dining table'
    assert infos[62]['color'] & 0xFF == 255

    # Meshes by stage, ground truth grey; the track box; one association segment camera -> object centre.
    assert component(chunks['/world/objects/chair_3'], 'albedo_factor') == [[rgba(rec.STAGE_COLOURS['dense'])]]
    assert component(chunks['/world/objects/dining_table_5'], 'albedo_factor') == [[rgba(rec.STAGE_COLOURS['sparse'])]]
    gt_entity = f'/world/ground_truth/{rec.object_key(chair.class_name, chair.id)}'
    assert all(static for static, _ in chunks[gt_entity])
    assert component(chunks[gt_entity], 'albedo_factor') == [[rgba(rec.GROUND_TRUTH_COLOUR[:3], 0.35)]]
    assert component(chunks['/world/tracks'], 'Boxes3D:labels') == [['chair 3']]
    strips = component(chunks['/world/associations'], 'LineStrips3D:strips')
    assert len(strips) == 1 and len(strips[0]) == 1
    camera = dict(frames)[middle][:3, 3]
    assert np.allclose(strips[0][0], [camera, chair.centroid], atol=1e-4)
    # Plots: final stage (2 dense, 1 sparse) at each object's time; both energies of each optimised stage.
    assert component(chunks['/plots/stage/chair_3'], 'Scalars:scalars') == [[2.0]]
    assert component(chunks['/plots/stage/dining_table_5'], 'Scalars:scalars') == [[1.0]]
    assert component(chunks['/plots/energy/chair_3/dense'], 'Scalars:scalars') == [[0.8, 0.5]]
    assert column(chunks['/plots/energy/chair_3/sparse'], 'stamp') == [middle]


def test_live_maps_clear_departed_objects_and_recolour_on_stage_change(tmp_path):
    recording = rec.FrodoRecording.open('save', tmp_path / 'live.rrd')
    t0 = 1_700_000_000_000_000_000
    recording.log_frame(t0, np.diag([100.0, 100.0, 1.0]), (64, 48), np.eye(4), np.zeros((48, 64, 3), np.uint8))
    tri = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    shown = recording.log_objects([rec.ObjectMesh(1, 'chair', *tri, t0), rec.ObjectMesh(2, 'chair', *tri, t0)])
    assert shown == {'world/objects/chair_1', 'world/objects/chair_2'}
    recording.log_states(t0 + 1, [rec.ObjectState(2, 'chair', 'sparse', 7)])
    assert recording.log_objects([rec.ObjectMesh(2, 'chair', *tri, t0 + 1)], t0 + 2) == {'world/objects/chair_2'}
    recording.log_boxes(t0 + 2, [rec.Track(2, 'chair', np.zeros(3), np.ones(3), 0.0)])
    recording.close()
    chunks, _ = read(tmp_path / 'live.rrd')
    chair1, chair2 = chunks['/world/objects/chair_1'], chunks['/world/objects/chair_2']
    assert component(chair1, 'Clear:is_recursive') == [[True]] and sorted(column(chair1, 'stamp')) == [t0, t0 + 2]
    assert not component(chair2, 'Clear:is_recursive')
    # fused (amber) first, then the stage change recolours it (sparse blue), and the next map keeps the colour
    assert timed(chair2, 'albedo_factor') == [(t, [rgba(rec.STAGE_COLOURS[s])])
                                              for t, s in ((t0, 'fused'), (t0 + 1, 'sparse'), (t0 + 1, 'sparse'))]
    assert column(chair1, 'frame')[0] == 1                 # stamped with the frame's stamp: on its frame too
    assert component(chunks['/world/objects/chair_2/box'], 'Boxes3D:centers') == [[[0.0, 0.0, 0.0]]]
    assert component(chunks['/plots/views/chair_2'], 'Scalars:scalars') == [[7.0]]


def test_vertex_normals_point_out_of_a_closed_mesh():
    box = trimesh.creation.box()
    normals = rec.vertex_normals(box.vertices, box.faces)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert (np.einsum('ij,ij->i', normals, box.vertices) > 0).all()
