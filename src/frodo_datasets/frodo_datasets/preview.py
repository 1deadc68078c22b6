"""Preview figure of a contract bag: a few frames as RGB, instance overlay and SLAM points + ground truth.

    python -m frodo_datasets.preview bags/demo_walk.mcap docs/synth_preview.png --frames 4

Reads the bag back with `frodo_common.bag.BagReader`, so the figure shows what a consumer of the bag sees.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.categories import category_by_id, split_instance_label
from frodo_common.conversions import (camera_info_to_K, cloud_to_xyz, image_to_numpy, image_to_rgb, marker_to_mesh,
                                      pose_to_matrix, stamp_to_ns)
from frodo_common.geometry import invert_transform, project_points


def _overlay(rgb: np.ndarray, instances: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) with each instance tinted by a colour hashed from its label value."""
    out = rgb.astype(np.float32) * 0.45
    for value in np.unique(instances):
        if value == 0:
            continue
        colour = np.random.default_rng(int(value)).uniform(60, 255, 3)
        out[instances == value] = 0.35 * rgb[instances == value] + 0.65 * colour
    return out.astype(np.uint8)


def save_preview(bag: str | Path, out: str | Path, frames: int = 4) -> Path:
    """Write a (3 x frames) figure of evenly spaced frames of `bag` to `out` (PNG)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    reader = BagReader(bag)
    by_stamp: dict[int, dict] = {}
    K = None
    gt, clouds = [], []
    for m in reader.messages():
        msg = m.decode()
        if m.topic == topics.GROUND_TRUTH:
            gt += [(mk.ns, mk.id, marker_to_mesh(mk)[0]) for mk in msg.markers]
        elif m.topic == topics.SLAM_POINTS:
            clouds.append((m.log_time_ns, cloud_to_xyz(msg)))
        elif m.topic == topics.CAMERA_INFO and K is None:
            K = camera_info_to_K(msg)
        elif m.topic in (topics.IMAGE, topics.INSTANCES, topics.POSE):
            by_stamp.setdefault(stamp_to_ns(msg.header.stamp), {})[m.topic] = msg
    stamps = [s for s in sorted(by_stamp) if len(by_stamp[s]) == 3]
    if not stamps or K is None:
        raise ValueError(f'{bag} has no complete frames (image + instances + pose + camera_info)')
    chosen = [stamps[int(i)] for i in np.linspace(0, len(stamps) - 1, frames).round()]
    fig, axes = plt.subplots(3, frames, figsize=(3.2 * frames, 7.4), squeeze=False)
    for col, stamp in enumerate(chosen):
        frame = by_stamp[stamp]
        rgb = image_to_rgb(frame[topics.IMAGE])
        inst = image_to_numpy(frame[topics.INSTANCES])
        T_cw = invert_transform(pose_to_matrix(frame[topics.POSE].pose))
        h, w = inst.shape
        axes[0, col].imshow(rgb)
        axes[0, col].set_title(f'frame t = {(stamp - stamps[0]) / 1e9:.1f} s', fontsize=9)
        axes[1, col].imshow(_overlay(rgb, inst))
        for value in np.unique(inst):
            if value == 0:
                continue
            coco, k = split_instance_label(int(value))
            ys, xs = np.nonzero(inst == value)
            cat = category_by_id(coco)
            axes[1, col].text(xs.mean(), ys.mean(), f'{cat.name if cat else coco} k={k}', fontsize=6,
                              color='white', ha='center', bbox={'facecolor': 'black', 'alpha': 0.5, 'pad': 1})
        axes[2, col].imshow(rgb // 3 + 80)
        cloud = [c for t, c in clouds if t <= stamp]
        if cloud:
            uv, z = project_points(K, T_cw, cloud[-1])
            ok = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            axes[2, col].scatter(uv[ok, 0], uv[ok, 1], s=0.15, c='yellow')
        for ns, object_id, vertices in gt:
            uv, z = project_points(K, T_cw, vertices[::7])
            ok = z > 0.1
            axes[2, col].scatter(uv[ok, 0], uv[ok, 1], s=0.2, c='cyan')
        axes[2, col].set_xlim(0, w)
        axes[2, col].set_ylim(h, 0)
        for row in range(3):
            axes[row, col].set_xticks([])
            axes[row, col].set_yticks([])
    axes[0, 0].set_ylabel('/camera/color/image_raw', fontsize=8)
    axes[1, 0].set_ylabel('/camera/instances', fontsize=8)
    axes[2, 0].set_ylabel('/slam/points (yellow)\n/ground_truth (cyan)', fontsize=8)
    fig.suptitle(f'{Path(bag).name}', fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: BAG OUT.png [--frames N]."""
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.preview', description=__doc__.splitlines()[0])
    parser.add_argument('bag', type=Path)
    parser.add_argument('out', type=Path)
    parser.add_argument('--frames', type=int, default=4)
    args = parser.parse_args(argv)
    print(save_preview(args.bag, args.out, args.frames))
    return 0


if __name__ == '__main__':
    sys.exit(main())
