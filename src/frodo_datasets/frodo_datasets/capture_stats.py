"""How a capture sees its objects: the statistics that tell a real walk from an easy synthetic one (issue 27).

    python -m frodo_datasets.capture_stats stats BAG.mcap [BAG2.mcap ...] [--markdown] [--json OUT]
    python -m frodo_datasets.eval_sets stats realwalk OUT [--variants full]     # one pooled row per set

From a bag's ground truth (the `/ground_truth/objects` meshes) and its `<stem>.gt.json` sidecar (intrinsics,
image size, the TRUE camera pose of every frame; `frodo_datasets.synth.write_sidecar`), per object:

- keyframes in view: frames in which at least `min_pixels` of the object are visible (not hidden by another
  ground-truth object; the sidecar's `min_mask_pixels`, the size below which `frodo synth` reports no
  instance);
- viewing-angle spread: the range of the azimuths (about world z) of the camera-to-object-centre rays over
  those frames, degrees (the smallest arc holding them all): 0 for an object always seen from one place,
  360 for an orbit;
- cut detections: frames in view in which a nearer ground-truth object hides at least `cut_threshold` of
  the object's unoccluded projection (ray casting against every mesh: the object alone vs. all objects);
  truncated ones: the unoccluded projection touches the image border;

and per capture the turn (rotation angle of the relative camera rotation, degrees) and the baseline (camera
centre distance, m) between consecutive frames (median and 90th percentile).

Only the ground-truth objects occlude (walls and unlabelled clutter do not), so "cut" counts what the issue
calls a detection cut by a nearer instance. No ROS, no rendering of colour: depth-only ray casts (embree).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh

CUT_THRESHOLD = 0.2


@dataclass
class ObjectStats:
    """One object: id, class, frames in view, azimuth spread (deg; None when never in view), detections cut
    by a nearer object and truncated by the image border (counts over the frames in view), and the mean
    fraction of its unoccluded projection hidden by nearer objects over those frames."""

    id: int
    class_name: str
    in_view: int
    spread_deg: float | None
    cut: int
    truncated: int
    hidden: float | None


@dataclass
class CaptureStats:
    """One capture: per-object statistics and the turns (deg) and baselines (m) between consecutive frames."""

    name: str
    frames: int
    objects: list[ObjectStats]
    turns_deg: list[float] = field(default_factory=list)
    baselines_m: list[float] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def azimuth_range(azimuths_deg: Sequence[float]) -> float | None:
    """Smallest arc (degrees, 0-360) holding every azimuth (degrees; wraps at +-180); None for no azimuths."""
    a = np.sort(np.mod(np.asarray(azimuths_deg, float), 360.0))
    if not len(a):
        return None
    gaps = np.diff(np.concatenate([a, [a[0] + 360.0]]))
    return float(360.0 - gaps.max())


def turns_and_baselines(poses: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (deg) of R_k^T R_k+1 and camera-centre distance (m) between consecutive poses
    T_world_camera (4, 4): arrays of len(poses) - 1."""
    poses = [np.asarray(T, float) for T in poses]
    turns, baselines = [], []
    for a, b in zip(poses[:-1], poses[1:]):
        cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
        turns.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        baselines.append(np.linalg.norm(b[:3, 3] - a[:3, 3]))
    return np.asarray(turns), np.asarray(baselines)


def _depth_map(caster, mesh: trimesh.Trimesh, K: np.ndarray, T: np.ndarray, width: int, height: int) -> np.ndarray:
    """z-depth (H, W) of one mesh seen alone from T_world_camera (inf where it is not hit); only the rays in
    the bounding box of its projected vertices are cast."""
    out = np.full((height, width), np.inf)
    cam = (mesh.vertices - T[:3, 3]) @ T[:3, :3]
    if not (cam[:, 2] > 1e-3).any():
        return out
    if (cam[:, 2] > 1e-3).all():
        uv = cam[:, :2] / cam[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        u0, v0 = np.floor(uv.min(axis=0)).astype(int)
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int)
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width - 1), min(v1, height - 1)
        if u0 > u1 or v0 > v1:
            return out
    else:  # straddles the camera plane: every ray
        u0, v0, u1, v1 = 0, 0, width - 1, height - 1
    v, u = np.mgrid[v0:v1 + 1, u0:u1 + 1]
    d_cam = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1], np.ones(u.size)], axis=1)
    dirs = d_cam @ T[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    loc, ray, _ = caster.intersects_location(np.broadcast_to(T[:3, 3], dirs.shape), dirs, multiple_hits=False)
    if len(ray):
        out[v.ravel()[ray], u.ravel()[ray]] = (loc - T[:3, 3]) @ T[:3, 2]
    return out


def capture_statistics(K: np.ndarray, width: int, height: int, poses: Sequence[np.ndarray],
                       objects: Sequence[tuple[int, str, trimesh.Trimesh]], min_pixels: int = 40,
                       cut_threshold: float = CUT_THRESHOLD, name: str = '') -> CaptureStats:
    """Statistics of a capture (module docstring): K (3, 3), image size, true poses T_world_camera (4, 4) per
    frame, ground-truth objects as (id, class name, world mesh)."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    K = np.asarray(K, float)
    casters = [RayMeshIntersector(mesh) for _, _, mesh in objects]
    centres = [mesh.bounds.mean(axis=0) for _, _, mesh in objects]
    n = len(objects)
    in_view = np.zeros(n, int)
    cut = np.zeros(n, int)
    truncated = np.zeros(n, int)
    hidden: list[list[float]] = [[] for _ in range(n)]
    azimuths: list[list[float]] = [[] for _ in range(n)]
    for T in poses:
        T = np.asarray(T, float)
        depth = np.stack([_depth_map(c, o[2], K, T, width, height) for c, o in zip(casters, objects)])
        nearest = np.argmin(depth, axis=0)
        hit = np.isfinite(depth.min(axis=0))
        for i in range(n):
            alone = np.isfinite(depth[i])
            visible = alone & hit & (nearest == i)
            if visible.sum() < min_pixels:
                continue
            in_view[i] += 1
            lost = 1.0 - visible.sum() / alone.sum()
            hidden[i].append(lost)
            cut[i] += lost >= cut_threshold
            truncated[i] += bool(alone[0].any() or alone[-1].any() or alone[:, 0].any() or alone[:, -1].any())
            ray = centres[i] - T[:3, 3]
            azimuths[i].append(np.degrees(np.arctan2(ray[1], ray[0])))
    turns, baselines = turns_and_baselines(poses)
    stats = [ObjectStats(int(oid), str(cls), int(in_view[i]), azimuth_range(azimuths[i]), int(cut[i]),
                         int(truncated[i]), float(np.mean(hidden[i])) if hidden[i] else None)
             for i, (oid, cls, _) in enumerate(objects)]
    return CaptureStats(name, len(poses), stats, [float(t) for t in turns], [float(b) for b in baselines])


def bag_statistics(bag: str | Path, cut_threshold: float = CUT_THRESHOLD) -> CaptureStats:
    """`capture_statistics` of a bag: ground-truth meshes from the bag, camera and true poses from its
    `<stem>.gt.json` sidecar (FileNotFoundError without one)."""
    from frodo_common.evaluation import load_ground_truth_bag
    from frodo_datasets.synth import sidecar_path

    bag = Path(bag)
    side = sidecar_path(bag)
    if not side.is_file():
        raise FileNotFoundError(f'{bag}: no ground-truth sidecar {side.name} (true camera poses) next to it')
    doc = json.loads(side.read_text())
    camera = doc['camera']
    poses = [np.asarray(f['T_world_camera'], float) for f in doc['frames']]
    min_pixels = int(doc.get('config', {}).get('min_mask_pixels', 40))
    objects = [(o.id, o.class_name, o.mesh) for o in load_ground_truth_bag(bag)]
    return capture_statistics(np.asarray(camera['K']), int(camera['width']), int(camera['height']), poses, objects,
                              min_pixels, cut_threshold, bag.stem)


def pool_statistics(captures: Sequence[CaptureStats]) -> dict:
    """Pooled over captures: objects; keyframes in view per object (median, 10th and 90th percentile, share of
    objects in 3-10 keyframes, share never in view); viewing-angle spread of the objects in view (median,
    90th percentile, deg); share of detections (frames in view) cut by a nearer object and truncated by the
    border; turn (deg) and baseline (cm) between consecutive frames (median, 90th percentile)."""
    objects = [o for c in captures for o in c.objects]
    views = np.array([o.in_view for o in objects], float)
    spread = np.array([o.spread_deg for o in objects if o.spread_deg is not None], float)
    seen = max(int(views.sum()), 1)
    turns = np.concatenate([c.turns_deg for c in captures]) if captures else np.zeros(0)
    baselines = 100.0 * np.concatenate([c.baselines_m for c in captures]) if captures else np.zeros(0)

    def q(a, p):
        return float(np.percentile(a, p)) if len(a) else None

    return {
        'captures': len(captures), 'frames': int(sum(c.frames for c in captures)), 'objects': len(objects),
        'in_view_median': q(views, 50), 'in_view_p10': q(views, 10), 'in_view_p90': q(views, 90),
        'in_view_3_10': float(np.mean((views >= 3) & (views <= 10))) if len(views) else None,
        'never_in_view': float(np.mean(views == 0)) if len(views) else None,
        'spread_median_deg': q(spread, 50), 'spread_p90_deg': q(spread, 90),
        'cut_fraction': sum(o.cut for o in objects) / seen,
        'truncated_fraction': sum(o.truncated for o in objects) / seen,
        'turn_median_deg': q(turns, 50), 'turn_p90_deg': q(turns, 90),
        'baseline_median_cm': q(baselines, 50), 'baseline_p90_cm': q(baselines, 90),
    }


HEADER = ('| captures | frames each | objects | keyframes in view per object: median (p10-p90) | objects in 3-10 '
          'keyframes | viewing-angle spread: median / p90 deg | detections cut by a nearer object | truncated | '
          'turn between keyframes: median / p90 deg | baseline: median / p90 cm |')


def markdown_row(label: str, pooled: dict) -> str:
    """One Markdown table row (after `HEADER` with a leading label column) of `pool_statistics`."""
    def f(key, spec='.0f'):
        v = pooled[key]
        return '-' if v is None else format(v, spec)

    frames = pooled['frames'] / max(pooled['captures'], 1)
    return (f'| {label} | {pooled["captures"]} | {frames:.0f} | {pooled["objects"]} | {f("in_view_median")} '
            f'({f("in_view_p10")}-{f("in_view_p90")}) | {100 * (pooled["in_view_3_10"] or 0):.0f} % | '
            f'{f("spread_median_deg")} / {f("spread_p90_deg")} | {100 * pooled["cut_fraction"]:.0f} % | '
            f'{100 * pooled["truncated_fraction"]:.0f} % | {f("turn_median_deg", ".1f")} / {f("turn_p90_deg", ".1f")} | '
            f'{f("baseline_median_cm", ".1f")} / {f("baseline_p90_cm", ".1f")} |')


def table_header(label: str = 'set') -> list[str]:
    head = HEADER.replace('| captures', f'| {label} | captures', 1)
    return [head, '|' + '---|' * (head.count('|') - 1)]


def object_lines(stats: CaptureStats) -> list[str]:
    """Human-readable per-object lines of one capture."""
    lines = []
    for o in stats.objects:
        spread = '-' if o.spread_deg is None else f'{o.spread_deg:.0f} deg'
        hidden = '-' if o.hidden is None else f'{100 * o.hidden:.0f} %'
        lines.append(f'  object {o.id} ({o.class_name}): in view in {o.in_view}/{stats.frames} frames, spread {spread}, '
                     f'{o.cut} cut by a nearer object (mean hidden {hidden}), {o.truncated} truncated')
    t, b = np.asarray(stats.turns_deg), 100 * np.asarray(stats.baselines_m)
    if len(t):
        lines.append(f'  turn median {np.median(t):.1f} / p90 {np.percentile(t, 90):.1f} deg, baseline median '
                     f'{np.median(b):.1f} / p90 {np.percentile(b, 90):.1f} cm')
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.capture_stats', description=__doc__.splitlines()[0])
    parser.add_argument('command', choices=('stats',))
    parser.add_argument('bags', nargs='+', type=Path, help='contract bags with /ground_truth/objects and a .gt.json sidecar')
    parser.add_argument('--cut-threshold', type=float, default=CUT_THRESHOLD,
                        help=f'hidden share of the projection that makes a detection "cut" (default {CUT_THRESHOLD})')
    parser.add_argument('--markdown', action='store_true', help='the pooled row as a Markdown table')
    parser.add_argument('--label', default='bags', help='label of the pooled row (default: bags)')
    parser.add_argument('--json', type=Path, default=None, help='also write per-capture and pooled statistics here')
    args = parser.parse_args(argv)
    captures = []
    for bag in args.bags:
        try:
            stats = bag_statistics(bag, args.cut_threshold)
        except (FileNotFoundError, ValueError) as err:
            print(f'{bag}: {err}', file=sys.stderr)
            return 1
        captures.append(stats)
        if not args.markdown:
            print(f'{bag}:')
            print('\n'.join(object_lines(stats)))
    pooled = pool_statistics(captures)
    if args.markdown:
        print('\n'.join(table_header() + [markdown_row(args.label, pooled)]))
    else:
        print('pooled: ' + json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in pooled.items()}))
    if args.json:
        args.json.write_text(json.dumps({'captures': [c.to_dict() for c in captures], 'pooled': pooled}, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
