"""Shared scene of the optimiser node tests: two chairs of the shipped prior, rendered from six viewpoints."""
import numpy as np
import pytest

from frodo_common.geometry import look_at
from frodo_datasets.render import Material, Renderer, RenderObject, intrinsics
from frodo_optim.sparse import pose_matrix
from frodo_shape.prior import ShapePrior

W, H = 160, 120
# Frame stamps in a recorded bag's time (2023-11-14, like bags/demo_walk.mcap), far from the wall clock: the
# node tests check that outputs keep the data's time.
BAG_EPOCH_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope='module')
def two_chairs():
    """Two chairs of the prior side by side (ids 1, 2), 6 textured views of both.

    Returns (K (3, 3), frames [(stamp_ns, rgb (H, W, 3), labels (H, W) uint16 = object id, T_world_camera)],
    boxes {id: (centre, size, yaw)}, codes {id: (64,) prior training code}).
    """
    prior = ShapePrior.load('furniture', device='cpu')
    chairs = [i for i, c in enumerate(prior.training_classes) if c == 'chair']
    objects, boxes, codes = [], {}, {}
    for oid, (index, x) in enumerate(((chairs[1], -0.5), (chairs[4], 0.6)), start=1):
        code = prior.training_codes[index].numpy()
        mesh = prior.mesh(code, resolution=40)
        s = 0.45
        T = pose_matrix(0.3 * oid, [x, 0.0, -s * mesh.bounds[0, 2]], s)
        world = mesh.copy().apply_transform(T)
        objects.append(RenderObject(world, Material(color=(0.2 + 0.3 * oid, 0.4, 0.3), kind='checker', scale=6), oid))
        lo, hi = world.bounds
        boxes[oid] = ((lo + hi) / 2, hi - lo, 0.3 * oid)
        codes[oid] = code
    renderer = Renderer(objects)
    K = intrinsics(W, H, 70.0)
    frames = []
    for k in range(6):
        a = -np.pi / 2 + (k - 2.5) * 0.25
        Twc = look_at([3.0 * np.cos(a), 3.0 * np.sin(a), 1.2], [0.0, 0.0, 0.4])
        out = renderer.render(K, Twc, W, H, shadows=False)
        frames.append((BAG_EPOCH_NS + 100_000_000 * k, out.rgb, out.labels.astype(np.uint16), Twc))
    return K, frames, boxes, codes
