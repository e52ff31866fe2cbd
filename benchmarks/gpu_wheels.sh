#!/usr/bin/env bash
# Run HERE (with PyPI) before benchmarks/gpu_check.sh: downloads into .whl/ (git-ignored) the wheels the GPU
# machine (Python 3.12, x86-64, no registry) lacks: gsplat and what matspray needs beside its torch (numpy, scipy,
# pillow, pyyaml, tqdm, jaxtyping, rich and ninja are on its image). Not Mitsuba: with drjit it is larger than
# the 64 MiB a call may carry, so the paper-scale object cannot be made there (benchmarks/gpu_check.sh says so).
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --platform manylinux1_x86_64 --platform any -d .whl \
  gsplat==1.5.3 pypng plyfile openexr pygltflib dataclasses-json marshmallow==3.26.2 trimesh==5.2.0
du -sh .whl
