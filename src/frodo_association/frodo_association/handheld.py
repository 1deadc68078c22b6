"""Handheld keyframe captures for evaluating association on real-capture conditions (issue 9; numpy/OpenCV,
no ROS, no mesh renderer).

A kitchen: one table with chairs around it, some pushed under the table top, small clutter boxes on the table
(undetected occluders), inside a room. Objects are built from boxes (table: top + 4 legs; chair: seat, back,
4 legs), so their silhouettes have holes and legs, and a chair under a table is seen through the gap below the
top. A handheld camera walks once around the table at close range (0.5-2 m from the objects, a Kinect-like
640x480 camera, fx = 525) over a 1000-frame sequence, looking at wandering points of the table; `n_keyframes`
frames spread over the sequence are kept, as a keyframe-based SLAM system would. Images are ray cast (exact
instance labels and optical depth), so objects are truncated by the image border in most views, as in real
captures.

Real-capture degradations (each optional):
- masks (`real_mask_noise`): edges moved by up to `boundary_px` (dilate/erode), holes, bleeding into the
  background on one side, missed detections;
- poses: tracking drift, a random walk over the whole sequence (translation and yaw) reaching about
  `drift_m` / `drift_deg` at its end (the associator sees the drifted poses);
- depth (`SynthFrame.depth`, metres, 0 = no measurement): Kinect-like axial noise, no measurement beyond
  4.5 m, closer than 0.45 m and at depth discontinuities;
- landmarks (`SynthScene.landmarks`): sparse SLAM points only on textured objects (`textured_prob`) and on
  the floor and walls, with 1 cm noise; the map holds every landmark (a consumer does not know which were
  seen in a frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from frodo_association.synthetic import CHAIR, TABLE, BoxObject, SynthFrame, SynthScene
from frodo_common.geometry import invert_transform, look_at

KINECT_SIZE = (640, 480)
ROOM_HALF = 3.5          # room walls at +-ROOM_HALF m, ceiling at ROOM_HEIGHT
ROOM_HEIGHT = 2.6


@dataclass
class Part:
    """A solid upright box of an object: world centre (3,), size (3,), yaw; label 0 = undetected clutter."""

    label_object: int          # object index, or -1 for clutter
    center: np.ndarray
    size: np.ndarray
    yaw: float


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(parts_local: list[tuple[tuple, tuple]], origin: np.ndarray, yaw: float, index: int) -> list[Part]:
    """Parts given as (local centre, size) in the object frame, placed at origin (floor point) with yaw."""
    R = _rot(yaw)
    return [Part(index, origin + R @ np.asarray(c, float), np.asarray(s, float), yaw) for c, s in parts_local]


def chair_parts(w: float, d: float, h: float, seat: float) -> list[tuple[tuple, tuple]]:
    """Seat, back (at local +y) and four legs of a chair w x d x h with the seat at height `seat`."""
    leg, t = 0.035, 0.04
    parts = [((0, 0, seat - t / 2), (w, d, t)), ((0, d / 2 - t / 2, (seat + h) / 2), (w, t, h - seat))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(((sx * (w - leg) / 2, sy * (d - leg) / 2, (seat - t) / 2), (leg, leg, seat - t)))
    return parts


def table_parts(length: float, width: float, h: float) -> list[tuple[tuple, tuple]]:
    """Top and four legs of a table length x width x h."""
    top, leg, inset = 0.04, 0.06, 0.08
    parts = [((0, 0, h - top / 2), (length, width, top))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(((sx * (length / 2 - inset), sy * (width / 2 - inset), (h - top) / 2), (leg, leg, h - top)))
    return parts


def kitchen(rng: np.random.Generator, n_chairs: int = 5, push: tuple[float, float] = (-0.1, 0.35),
            clutter: int = 4) -> tuple[list[BoxObject], list[Part], np.ndarray]:
    """A table (index 0) with `n_chairs` chairs around it facing it, pushed towards it by a random amount in
    `push` (m; above about 0.35 the seat is under the table top), and `clutter` small boxes on the top.
    Returns (ground-truth upright boxes, solid parts, table footprint half-extent (2,))."""
    length, width, height = rng.uniform(1.2, 2.0), rng.uniform(0.75, 1.0), rng.uniform(0.72, 0.78)
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    R0 = _rot(yaw0)
    objects = [BoxObject(TABLE, np.array([0.0, 0.0, height / 2]), np.array([length, width, height]), yaw0)]
    parts = _place(table_parts(length, width, height), np.zeros(3), yaw0, 0)
    n_long = 2 if length >= 1.4 else 1
    slots = [(x, s) for s in (-1, 1) for x in np.linspace(-length / 4, length / 4, n_long) * (n_long > 1)] \
        + [('end', -1), ('end', 1)]
    order = rng.permutation(len(slots))[:n_chairs]
    for k, j in enumerate(order):
        w, d, h = rng.uniform(0.42, 0.52), rng.uniform(0.45, 0.55), rng.uniform(0.8, 0.98)
        p = rng.uniform(*push)
        x, s = slots[j]
        if x == 'end':          # at an end of the table, facing along its length
            gap = length / 2 + d / 2 + 0.12 - p
            local, face = np.array([s * gap, 0.0]), (-s * np.pi / 2 + np.pi)
        else:
            gap = width / 2 + d / 2 + 0.12 - p
            local, face = np.array([x, s * gap]), (0.0 if s > 0 else np.pi)
        yaw = yaw0 + face + float(rng.normal(0, np.radians(10)))
        origin = np.array([*(R0[:2, :2] @ local), 0.0])
        parts += _place(chair_parts(w, d, h, rng.uniform(0.43, 0.48)), origin, yaw, k + 1)
        # Ground truth: the chair's upright box (its seat centre is at local (0, 0); the back is inside d).
        objects.append(BoxObject(CHAIR, origin + np.array([0.0, 0.0, h / 2]), np.array([w, d, h]), yaw))
    for _ in range(clutter):
        size = rng.uniform([0.06, 0.06, 0.08], [0.3, 0.25, 0.3])
        xy = rng.uniform(-0.4, 0.4, 2) * [length - size[0], width - size[1]]
        parts.append(Part(-1, np.array([*(R0[:2, :2] @ xy), height + size[2] / 2]), size,
                          float(rng.uniform(-np.pi, np.pi))))
    return objects, parts, np.array([length, width]) / 2


def handheld_path(rng: np.random.Generator, n_frames: int, half_extent: np.ndarray, near: float = 0.5,
                  far: float = 1.6, sweep_deg: float = 330.0) -> np.ndarray:
    """T_world_camera (F, 4, 4): one walk around the table centre, `near`-`far` m beyond the table's footprint
    radius, 1.1-1.6 m high, looking at points wandering over the table, with hand roll and pitch jitter."""
    t = np.linspace(0.0, 1.0, n_frames)
    phase = rng.uniform(0, 2 * np.pi, 6)
    start = rng.uniform(0, 2 * np.pi)
    ang = start + np.radians(sweep_deg) * t
    foot = float(np.hypot(*half_extent))
    dist = foot + near + (far - near) * (0.5 + 0.5 * np.sin(2 * np.pi * 2.3 * t + phase[0]))
    height = rng.uniform(1.2, 1.5) + 0.1 * np.sin(2 * np.pi * 3.1 * t + phase[1])
    target = np.stack([half_extent[0] * 0.8 * np.sin(2 * np.pi * 1.7 * t + phase[2]),
                       half_extent[1] * 0.8 * np.sin(2 * np.pi * 2.9 * t + phase[3]),
                       0.45 + 0.2 * np.sin(2 * np.pi * 4.3 * t + phase[4])], axis=1)
    roll = np.radians(4.0) * np.sin(2 * np.pi * 5.3 * t + phase[5])
    poses = []
    for k in range(n_frames):
        eye = np.array([dist[k] * np.cos(ang[k]), dist[k] * np.sin(ang[k]), height[k]])
        T = look_at(eye, target[k])
        c, s = np.cos(roll[k]), np.sin(roll[k])
        T[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])      # roll about the optical axis
        poses.append(T)
    return np.array(poses)


def raycast(parts: list[Part], K: np.ndarray, T_world_camera: np.ndarray,
            size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast the parts inside the room: (object index per pixel (H, W) int (-1: background or clutter),
    optical depth (H, W) float32 in metres, of the nearest surface, walls and floor included)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    R, o = T_world_camera[:3, :3], T_world_camera[:3, 3]
    d = d_cam @ R.T                                  # world directions with optical-depth parametrisation
    # Room: exit distance of the room box (floor, walls, ceiling).
    lo, hi = np.array([-ROOM_HALF, -ROOM_HALF, 0.0]), np.array([ROOM_HALF, ROOM_HALF, ROOM_HEIGHT])
    with np.errstate(divide='ignore', invalid='ignore'):
        t_exit = np.min(np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf)), axis=-1)
    depth = t_exit
    index = np.full((h, w), -1, np.int64)
    T_cw = invert_transform(T_world_camera)
    for part in parts:
        corners = part.center + (np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
                                 * part.size) @ _rot(part.yaw).T
        pc = corners @ T_cw[:3, :3].T + T_cw[:3, 3]
        if np.all(pc[:, 2] < 0.05):
            continue
        if np.all(pc[:, 2] > 0.05):                   # cull to the projected rectangle
            uu = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
            vv = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
            x0, x1 = int(max(np.floor(uu.min()), 0)), int(min(np.ceil(uu.max()) + 1, w))
            y0, y1 = int(max(np.floor(vv.min()), 0)), int(min(np.ceil(vv.max()) + 1, h))
        else:
            x0, x1, y0, y1 = 0, w, 0, h
        if x0 >= x1 or y0 >= y1:
            continue
        Rb = _rot(-part.yaw)
        dl = d[y0:y1, x0:x1] @ Rb.T
        ol = Rb @ (o - part.center)
        half = part.size / 2
        with np.errstate(divide='ignore', invalid='ignore'):
            t1, t2 = (-half - ol) / dl, (half - ol) / dl
        tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit = (tmax >= np.maximum(tmin, 0.05)) & (tmin > 0.05) & (tmin < depth[y0:y1, x0:x1])
        depth[y0:y1, x0:x1] = np.where(hit, tmin, depth[y0:y1, x0:x1])
        index[y0:y1, x0:x1] = np.where(hit, part.label_object, index[y0:y1, x0:x1])
    return index, depth.astype(np.float32)


def kinect_depth(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like depth (metres, 0 = no measurement): axial noise sigma = 1.2 mm + 1.9 mm (z - 0.4)^2 per metre^2,
    no measurement closer than 0.45 m, beyond 4.5 m and at depth discontinuities (edges)."""
    z = depth.astype(np.float64)
    noisy = z + rng.normal(size=z.shape) * (0.0012 + 0.0019 * (z - 0.4) ** 2)
    jump = np.maximum(np.abs(cv2.Sobel(z, cv2.CV_64F, 1, 0, ksize=3)), np.abs(cv2.Sobel(z, cv2.CV_64F, 0, 1, ksize=3)))
    bad = (z < 0.45) | (z > 4.5) | (jump > 0.4 * z)
    return np.where(bad, 0.0, np.round(noisy * 1000) / 1000).astype(np.float32)


def real_mask_noise(instances: np.ndarray, rng: np.random.Generator, boundary_px: int = 4, hole_prob: float = 0.3,
                    bleed_prob: float = 0.3, miss_rate: float = 0.1) -> np.ndarray:
    """Real-detector masks: per instance, edges moved by a random radius in [-boundary_px, boundary_px], with
    probability `hole_prob` one or two elliptic holes, with `bleed_prob` bleeding 8-24 px into the background on
    one side; instances missed at `miss_rate`. Nearer instances (painted later) are not favoured: an instance
    only takes pixels that no earlier instance holds."""
    out = np.zeros_like(instances)
    h, w = instances.shape
    for lab in np.unique(instances[instances > 0]):
        if rng.random() < miss_rate:
            continue
        mask = (instances == lab).astype(np.uint8)
        ys, xs = np.nonzero(mask)
        r = int(rng.integers(-boundary_px, boundary_px + 1)) if boundary_px > 0 else 0
        if r:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(r) + 1, 2 * abs(r) + 1))
            mask = cv2.dilate(mask, kernel) if r > 0 else cv2.erode(mask, kernel)
        side = max(min(xs.max() - xs.min(), ys.max() - ys.min()), 1)
        if rng.random() < hole_prob:
            for _ in range(int(rng.integers(1, 3))):
                k = int(rng.integers(len(xs)))
                axes = tuple(int(a) for a in np.maximum(rng.uniform(0.06, 0.15, 2) * side, 2))
                cv2.ellipse(mask, (int(xs[k]), int(ys[k])), axes, float(rng.uniform(0, 180)), 0, 360, 0, -1)
        if rng.random() < bleed_prob:
            rad = int(rng.integers(8, 25))
            grown = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1)))
            a = rng.uniform(0, 2 * np.pi)
            yy, xx = np.mgrid[0:h, 0:w]
            half = (xx - xs.mean()) * np.cos(a) + (yy - ys.mean()) * np.sin(a) > 0
            mask = np.where(half, grown, mask)
        out[(mask > 0) & (out == 0)] = lab
    return out


def _drift(n: int, rng: np.random.Generator, drift_m: float, drift_deg: float) -> np.ndarray:
    """(n, 4, 4) world-frame drift transforms: random walks ending at about drift_m (translation, per axis
    scale) and drift_deg (yaw)."""
    steps_t = rng.normal(size=(n, 3)) * drift_m / np.sqrt(n)
    steps_t[:, 2] *= 0.3                                 # gravity-aware tracking drifts less in height
    steps_y = rng.normal(size=n) * np.radians(drift_deg) / np.sqrt(n)
    t, yaw = np.cumsum(steps_t, axis=0), np.cumsum(steps_y)
    out = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        out[k, :3, :3] = _rot(yaw[k])
        out[k, :3, 3] = t[k]
    return out


def landmarks(parts: list[Part], rng: np.random.Generator, textured_prob: float = 0.6, density: float = 120.0,
              background_density: float = 4.0) -> np.ndarray:
    """Sparse SLAM landmarks (P, 3) with 1 cm noise: on the surfaces of the parts of textured objects
    (`density` per m^2; each object is textured with probability `textured_prob`, clutter always), and on the
    floor and walls (`background_density` per m^2)."""
    textured = {}
    pts = []
    for p in parts:
        if p.label_object not in textured:
            textured[p.label_object] = p.label_object < 0 or rng.random() < textured_prob
        if not textured[p.label_object]:
            continue
        area = 2 * (p.size[0] * p.size[1] + p.size[1] * p.size[2] + p.size[0] * p.size[2])
        n = rng.poisson(density * area)
        local = rng.uniform(-0.5, 0.5, (n, 3)) * p.size
        axis = rng.integers(0, 3, n)                      # snap each point to a face
        local[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n)) * p.size[axis] / 2
        pts.append(p.center + local @ _rot(p.yaw).T)
    floor = rng.uniform(-ROOM_HALF, ROOM_HALF, (rng.poisson(background_density * (2 * ROOM_HALF) ** 2), 3))
    floor[:, 2] = 0.0
    pts.append(floor)
    for wall in range(4):
        n = rng.poisson(background_density * 2 * ROOM_HALF * ROOM_HEIGHT)
        q = np.stack([rng.uniform(-ROOM_HALF, ROOM_HALF, n), np.full(n, ROOM_HALF), rng.uniform(0, ROOM_HEIGHT, n)], 1)
        pts.append(q @ _rot(wall * np.pi / 2).T)
    out = np.concatenate(pts)
    return out + rng.normal(0, 0.01, out.shape)


_RENDER_CACHE: dict[tuple, tuple] = {}


def _render(seed: int, n_chairs: int, n_keyframes: int, sequence_frames: int, near: float, far: float,
            push: tuple[float, float], clutter: int, textured_prob: float) -> tuple:
    """Geometry, keyframes and exact renders of a seeded kitchen (cached per process: conditions that only
    change the degradations reuse them)."""
    key = (seed, n_chairs, n_keyframes, sequence_frames, near, far, tuple(push), clutter, textured_prob)
    if key not in _RENDER_CACHE:
        rng = np.random.default_rng(seed)
        objects, parts, half = kitchen(rng, n_chairs, push, clutter)
        K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1.0]])
        poses = handheld_path(rng, sequence_frames, half, near, far)
        spacing = sequence_frames / n_keyframes
        keys = np.unique(np.clip(np.round((np.arange(n_keyframes) + 0.5 + rng.uniform(-0.3, 0.3, n_keyframes))
                                          * spacing), 0, sequence_frames - 1).astype(int))
        renders = [raycast(parts, K, poses[k], KINECT_SIZE) for k in keys]
        if len(_RENDER_CACHE) > 64:
            _RENDER_CACHE.clear()
        _RENDER_CACHE[key] = (objects, K, poses, keys, renders, landmarks(parts, rng, textured_prob))
    return _RENDER_CACHE[key]


def make_handheld_scene(seed: int, n_chairs: int = 5, n_keyframes: int = 35, sequence_frames: int = 1000,
                        near: float = 0.5, far: float = 1.6, push: tuple[float, float] = (-0.1, 0.35),
                        clutter: int = 4, boundary_px: int = 0, hole_prob: float = 0.0, bleed_prob: float = 0.0,
                        miss_rate: float = 0.0, drift_m: float = 0.0, drift_deg: float = 0.0,
                        with_depth: bool = True, textured_prob: float = 0.6, fps: float = 30.0) -> SynthScene:
    """A seeded kitchen seen by `n_keyframes` keyframes spread over a `sequence_frames` handheld sequence
    (640x480, fx = 525). Frames carry ground truth (instance label -> object index; visibility is not
    computed: empty) and optionally depth; the scene carries the landmarks. The geometry depends only on
    `seed` and the layout arguments; the degradations use their own seeded generator, so conditions of one seed
    see the same kitchen and path."""
    objects, K, poses, keys, renders, points = _render(seed, n_chairs, n_keyframes, sequence_frames, near, far,
                                                       push, clutter, textured_prob)
    rng = np.random.default_rng([seed, 1])
    drift = _drift(sequence_frames, rng, drift_m, drift_deg) if (drift_m or drift_deg) else None
    w, h = KINECT_SIZE
    frames = []
    for k, (index, depth) in zip(keys, renders):
        T = poses[k]
        instances = np.zeros((h, w), np.uint16)
        gt: dict[int, int] = {}
        for n, i in enumerate(np.unique(index[index >= 0])):
            label = objects[i].coco_id * 256 + n + 1
            instances[index == i] = label
            gt[label] = int(i)
        if boundary_px or hole_prob or bleed_prob or miss_rate:
            instances = real_mask_noise(instances, rng, boundary_px, hole_prob, bleed_prob, miss_rate)
            present = set(np.unique(instances).tolist())
            gt = {lab: i for lab, i in gt.items() if lab in present}
        observed = drift[k] @ T if drift is not None else T.copy()
        frames.append(SynthFrame(int(1e9 + k * 1e9 / fps), K, T, observed, (w, h), instances, gt, {},
                                 kinect_depth(depth, rng) if with_depth else None))
    return SynthScene(objects, frames, points)
