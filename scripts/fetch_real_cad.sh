#!/usr/bin/env bash
# Fetch the held-out real-CAD split of data/real/README.md: artist-made models of real furniture products from
# the AWS RoboMaker small-house and bookstore worlds (MIT-0), cloned at pinned commits into SRC (default
# data/real/build/src, git-ignored; the small-house clone is the one scripts/build_real_bags.sh uses).
#
# usage: scripts/fetch_real_cad.sh [SRC]
# AWS_HOUSE_URL / AWS_BOOKSTORE_URL override the clone sources (e.g. local mirrors; AWS_URL, build_real_bags.sh's
# name, is honoured for the small house too). Needs git, network access to github.com (only for the clones) and
# `make setup`'s .venv; pycollada (to read the COLLADA meshes) is installed into SRC/pydeps, not into the
# project's environment. Then score a prior on the split:
#   OMP_NUM_THREADS=1 PYTHONPATH=SRC/pydeps .venv/bin/python -m frodo_shape.evaluate_prior --prior furniture \
#       --real-cad SRC --heldout 0 --train-count 0 --views 0 --out real_cad.json
set -euo pipefail
cd "$(dirname "$0")/.."
SRC=${1:-data/real/build/src}
PY=${PYTHON:-.venv/bin/python}

AWS_HOUSE_URL=${AWS_HOUSE_URL:-${AWS_URL:-https://github.com/aws-robotics/aws-robomaker-small-house-world}}
AWS_HOUSE_COMMIT=dd44be6205b2e6577bf641300dacc1699cb2ca81
AWS_BOOKSTORE_URL=${AWS_BOOKSTORE_URL:-https://github.com/aws-robotics/aws-robomaker-bookstore-world}
AWS_BOOKSTORE_COMMIT=ed542eb41809d5c5f1c67f32d4ba24e0e90886b3

clone_at() {  # URL COMMIT DIR: a checkout of exactly COMMIT
    if [ ! -d "$3/.git" ]; then
        git clone --quiet --no-checkout "$1" "$3"
    fi
    git -C "$3" -c advice.detachedHead=false checkout --quiet "$2"
}

mkdir -p "$SRC"
clone_at "$AWS_HOUSE_URL" "$AWS_HOUSE_COMMIT" "$SRC/aws-robomaker-small-house-world"
clone_at "$AWS_BOOKSTORE_URL" "$AWS_BOOKSTORE_COMMIT" "$SRC/aws-robomaker-bookstore-world"
if ! PYTHONPATH="$SRC/pydeps" "$PY" -c 'import collada' 2>/dev/null; then
    "$PY" -m pip install --quiet --no-deps --target "$SRC/pydeps" pycollada==0.9.3
fi
echo "real-CAD split sources in $SRC (pycollada in $SRC/pydeps)"
