#!/usr/bin/env bash
# Rebuild the public-source development bags of data/real/README.md:
# AWS RoboMaker small-house furniture (MIT-0) rendered along the TUM RGB-D fr1/xyz hand-held trajectory
# (CC BY 4.0), 35 and 120 frames per scene, into OUT (default data/real/build, git-ignored).
#
# usage: scripts/build_real_bags.sh [OUT] [SRC]
#   SRC (default OUT/src): where the two source repositories are cloned at their pinned commits.
# AWS_URL / TUM_URL override the clone sources (e.g. local mirrors). Needs git, network access to github.com
# (only for the clones) and `make setup`'s .venv; pycollada (to read the COLLADA meshes) is installed into
# SRC/pydeps, not into the project's environment.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/real/build}
SRC=${2:-$OUT/src}
PY=${PYTHON:-.venv/bin/python}

AWS_URL=${AWS_URL:-https://github.com/aws-robotics/aws-robomaker-small-house-world}
AWS_COMMIT=dd44be6205b2e6577bf641300dacc1699cb2ca81
TUM_URL=${TUM_URL:-https://github.com/Khashayar-Gh/RGBD_Localization}
TUM_COMMIT=37c66d15d653a7c425392cdbe5cac661dc72a838

clone_at() {  # URL COMMIT DIR: a checkout of exactly COMMIT
    if [ ! -d "$3/.git" ]; then
        git clone --quiet --no-checkout "$1" "$3"
    fi
    git -C "$3" -c advice.detachedHead=false checkout --quiet "$2"
}

mkdir -p "$SRC" "$OUT"
clone_at "$AWS_URL" "$AWS_COMMIT" "$SRC/aws-robomaker-small-house-world"
clone_at "$TUM_URL" "$TUM_COMMIT" "$SRC/RGBD_Localization"
if ! PYTHONPATH="$SRC/pydeps" "$PY" -c 'import collada' 2>/dev/null; then
    "$PY" -m pip install --quiet --no-deps --target "$SRC/pydeps" pycollada==0.9.3
fi
OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} PYTHONPATH="$SRC/pydeps" "$PY" -m frodo_datasets.real_data \
    --aws "$SRC/aws-robomaker-small-house-world" --tum "$SRC/RGBD_Localization/groundtruth.txt" \
    --out "$OUT" --scenes aws_dining,aws_balcony --frames 35,120
