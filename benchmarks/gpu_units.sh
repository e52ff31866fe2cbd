#!/usr/bin/env bash
# The GPU checks of refinement and lifting in one call (a shorter gpu_check.sh, made to finish within 9 minutes on one
# H100-class GPU), the code before the change timed on the same machine:
#   1. install the carried wheels (.whl/, benchmarks/gpu_wheels.sh) and build gsplat's CUDA extension (with
#      GSPLAT_PREBUILT=FILE, an earlier call's build of it on the same image, is loaded instead; a new build is kept
#      in OUT/gsplat_cuda.so.xz for the next call: benchmarks/gsplat_prebuilt/use.sh);
#   2. the device tests of refinement's graphs and lifting's kernel, and the whole method on CUDA (pytest --device
#      cuda; the tiny object from MATSPRAY_TINY_OBJECT);
#   3. python -m benchmarks.step_cost --device cuda --units refine lift: operations, launches and waits per unit
#      (GPU_UNITS_STEP_COST=0: not run);
#   4. python -m benchmarks.unit_rates on GPU_CHECK_DATA (a carried `matspray synth` object): Gaussian Splatting
#      trained once (its Gaussians saved), lifting (with and without the rays' kernel; GPU_UNITS_LIFT_UNFUSED=0:
#      with it only) and refinement rates;
#   5. with GPU_UNITS_BEFORE=DIR (the earlier package's matspray/ and benchmarks/, e.g. `git archive`): its lifting and
#      refinement rates on the same Gaussians, in another process;
#   6. one summary.
#     GPU_CHECK_DATA=.gpu-data/obj512 GPU_UNITS_BEFORE=.gpu-data/head bash benchmarks/gpu_units.sh OUT_DIR
set -uo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
OUT=${1:-${OUT:-runs/gpu-units}}
mkdir -p "$OUT"
START=$(date +%s)
BUDGET=${GPU_UNITS_SECONDS:-520}
cap() { local left=$((BUDGET - ($(date +%s) - START) - 15)); [ "$1" -lt "$left" ] && echo "$1" || echo $((left > 1 ? left : 1)); }
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
SITE=$REPO
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "installing the carried wheels failed"; exit 1; }
  SITE=/tmp/site:$REPO
fi
source benchmarks/gsplat_prebuilt/use.sh  # GSPLAT_PREBUILT: an earlier call's build of gsplat, loaded, not compiled
export PYTHONPATH=$SITE
summary=()
quiet() { grep -v -E "Warning|warn\(|return Variable|^\s*$"; }

python3 -c "import torch; print('torch', torch.__version__, 'on', torch.cuda.get_device_name())" | tee "$OUT/device.txt"
timeout "$(cap 200)" python3 -c "
import time; start = time.perf_counter()
from gsplat.cuda._backend import _C
from matspray.render.backend import resolve_backend
print(f'gsplat built in {time.perf_counter() - start:.0f} s; auto on cuda: {resolve_backend(\"auto\", \"cuda\")}')
" 2>&1 | quiet | tail -n 2 | tee "$OUT/gsplat.txt"
summary+=("$(cat "$OUT/device.txt") | $(tail -n 1 "$OUT/gsplat.txt")")
gsplat_keep_build "$OUT"

timeout "$(cap 150)" python3 -m pytest -q -p no:cacheprovider --device cuda -m on_device tests/test_refine_terms.py \
  tests/test_cuda_rays.py tests/test_device.py tests/test_bilinear.py tests/test_merger.py 2>&1 | tee "$OUT/pytest_cuda.log" | tail -n 25
summary+=("pytest --device cuda (refine terms, rays kernel, device): $(tail -n 1 "$OUT/pytest_cuda.log")")

if [ "${GPU_UNITS_STEP_COST:-1}" = 1 ]; then
  timeout "$(cap 90)" python3 -m benchmarks.step_cost --device cuda --units refine lift --json "$OUT/step_cost.json" 2>&1 \
    | quiet | tee "$OUT/step_cost.log"
  summary+=("step_cost on CUDA:" "$(grep -E '^(unit|per )' "$OUT/step_cost.log")")
fi

if [ -n "${GPU_CHECK_DATA:-}" ]; then
  nvidia-smi dmon -s u -d 1 >"$OUT/dmon.log" 2>&1 &
  dmon=$!
  timeout "$(cap 200)" python3 -m benchmarks.unit_rates --data "$GPU_CHECK_DATA" --device cuda --geometry-steps 7000 \
    --refine-steps "${GPU_UNITS_REFINE_STEPS:-600}" --warmup-steps 100 $([ "${GPU_UNITS_LIFT_UNFUSED:-1}" = 1 ] && echo --lift-unfused) --out /tmp/gpu-units \
    --save-gaussians /tmp/gpu-units/gaussians.pt --json "$OUT/unit_rates.json" 2>&1 | tr '\r' '\n' | quiet \
    | tee "$OUT/unit_rates.log"
  kill $dmon 2>/dev/null
  summary+=("unit rates, this code (exit ${PIPESTATUS[0]}):" "$(tail -n 6 "$OUT/unit_rates.log")")
  summary+=("SM utilisation meanwhile: $(awk '$1 !~ /#/ && NF > 2 {s += $2; n++} END {if (n) printf "%.0f %% over %d s", s / n, n}' "$OUT/dmon.log")")
  if [ -n "${GPU_UNITS_BEFORE:-}" ] && [ -f /tmp/gpu-units/gaussians.pt ]; then
    (cd "$GPU_UNITS_BEFORE" && PYTHONPATH="${SITE/$REPO/$REPO/$GPU_UNITS_BEFORE}" timeout "$(cap 150)" python3 - \
      "$REPO/$GPU_CHECK_DATA" /tmp/gpu-units/gaussians.pt "${GPU_UNITS_REFINE_STEPS:-600}" <<'EOF'
import sys

import torch

from benchmarks.unit_rates import lift_seconds_per_view, refine_rates
from matspray.method.config import build_config
from matspray.data.loader import load_scene
from matspray.gaussians import Gaussians
from matspray.geometry.train import prepare_views
from matspray.render.backend import rendering_with, resolve_backend

data, saved, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
device = torch.device("cuda")
tensors = torch.load(saved)
gaussians = Gaussians(*(tensors[k] for k in ("means", "log_scales", "quats", "opacity_logits", "sh"))).to(device)
config = build_config("paper").geometry
with rendering_with(resolve_backend("auto", device)):
    views = [v.to(device) for v in prepare_views(load_scene(data).train, config.resolution)]
    print(f"before: lifting, 16x16 rays per pixel: {lift_seconds_per_view(gaussians, views, device, 16):.3f} s per view",
          flush=True)
    rates = refine_rates(gaussians, views, device, 100, steps)
    print("before: " + ", ".join(f"{k} {v:.1f} steps/s" for k, v in rates.items()), flush=True)
EOF
    ) 2>&1 | quiet | tee "$OUT/unit_rates_before.log"
    summary+=("the code before, same Gaussians:" "$(grep '^before' "$OUT/unit_rates_before.log")")
  fi
fi

echo
echo "==================== gpu_units summary ($(( $(date +%s) - START )) s) ===================="
printf '%s\n' "${summary[@]}"
