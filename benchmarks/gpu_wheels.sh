#!/usr/bin/env bash
# Run HERE (with PyPI) before benchmarks/gpu_check.sh: downloads into .whl/ (git-ignored) the wheels the GPU
# machine (Python 3.12, x86-64, no registry) lacks: gsplat and what matspray needs beside its torch (numpy, scipy,
# pillow, pyyaml, tqdm, jaxtyping, rich and ninja are on its image). Mitsuba's and drjit's wheels (67 MB together, more
# than the 64 MiB a call may carry) go to .mitsuba-wheels/ and are cut down to the variants and plugins `synth` renders
# the demo object with (benchmarks/mitsuba_reduced.py): .gpu-data/mitsuba.tar.xz, which benchmarks/gpu_check.sh unpacks
# there, so that the paper preset's 100-view 512 px object is made on the GPU machine (its cuda_ad_rgb variant).
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --platform manylinux1_x86_64 --platform any -d .whl \
  gsplat==1.5.3 pypng plyfile openexr pygltflib dataclasses-json marshmallow==3.26.2 trimesh==5.2.0
du -sh .whl
grep -qx '/.mitsuba-wheels/' .git/info/exclude 2>/dev/null || echo /.mitsuba-wheels/ >> .git/info/exclude
versions=$(python3 -c "import mitsuba, drjit; print(f'mitsuba=={mitsuba.__version__} drjit=={drjit.__version__}')")
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .mitsuba-wheels $versions
mkdir -p .gpu-data
python3 -m benchmarks.mitsuba_reduced --wheels .mitsuba-wheels/*cp312*.whl --out .gpu-data/mitsuba.tar.xz
