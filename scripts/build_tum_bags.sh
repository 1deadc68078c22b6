#!/usr/bin/env bash
# Rebuild the real-frame development bags of data/real/README.md ("Real frames: TUM RGB-D with annotated masks"):
# TUM RGB-D fr1/rpy (723 frames, a desk) and fr3/cabinet (58 keyframes) (both CC BY 4.0), instance masks made by
# frodo_datasets.annotate from the committed boxes in data/real/annotations/, into OUT (default data/real/build).
#
# usage: scripts/build_tum_bags.sh [OUT] [SRC]
#   SRC (default OUT/src): where the two source repositories are cloned at their pinned commits (data/ only).
# RPY_URL / CABINET_URL override the clone sources (e.g. local mirrors). Then measure:
#   .venv/bin/python -m frodo_datasets.annotate measure OUT/tum_*.mcap --out OUT/runs --readme data/real/README.md
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/real/build}
SRC=${2:-$OUT/src}
PY=${PYTHON:-.venv/bin/python}

RPY_URL=${RPY_URL:-https://github.com/jmstark/gpu_odometry}
RPY_COMMIT=aec7c853676c7d809d9fd89e728c3f54b725a63e
CABINET_URL=${CABINET_URL:-https://github.com/benchun123/cuboid_slam_with_bbox_constraints}
CABINET_COMMIT=d228cfa2cd2bae42d568ee573165999977cc5e61

clone_data_at() {  # URL COMMIT DIR: a checkout of exactly COMMIT, data/ only
    if [ ! -d "$3/.git" ]; then
        git clone --quiet --no-checkout "$1" "$3"
    fi
    git -C "$3" sparse-checkout set data
    git -C "$3" -c advice.detachedHead=false checkout --quiet "$2"
}

mkdir -p "$SRC" "$OUT"
clone_data_at "$RPY_URL" "$RPY_COMMIT" "$SRC/gpu_odometry"
clone_data_at "$CABINET_URL" "$CABINET_COMMIT" "$SRC/cuboid_slam_with_bbox_constraints"
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
"$PY" -m frodo_datasets.annotate build data/real/annotations/tum_fr1_rpy.json "$SRC/gpu_odometry/data" \
    "$OUT/tum_fr1_rpy_desk_35.mcap" --views 35 --resize 0.5 --voxel 0.02 --every-fuse 4
"$PY" -m frodo_datasets.annotate build data/real/annotations/tum_fr3_cabinet.json \
    "$SRC/cuboid_slam_with_bbox_constraints/data" "$OUT/tum_fr3_cabinet_58.mcap" --resize 0.5 --voxel 0.01 --every-fuse 1
