#!/usr/bin/env bash
# Every GPU check of MatSpray in one call, built to finish within 10 minutes on one H100-class GPU:
#   1. install what the machine lacks (wheels carried in .whl/, made here by benchmarks/gpu_wheels.sh) and matspray itself;
#   2. build gsplat's CUDA extension (timed; with GSPLAT_PREBUILT=FILE an earlier call's build is loaded instead, and a
#      new build is kept in OUT/gsplat_cuda.so.xz for the next call: benchmarks/gsplat_prebuilt/use.sh) and check that
#      backend `auto` picks it;
#   3. the test suite's device tests on CUDA (pytest --device cuda: the on_device tests, the gsplat parity tests, the
#      graphed training step);
#   4. python -m benchmarks.step_cost --device cuda: operations and synchronisations per unit of work, counted there;
#   5. with GPU_CHECK_DATA=DIR (a `matspray synth` object made elsewhere, e.g. 12 views at 512 px): the per-unit rates
#      of the paper preset on it and the whole preset projected from them (python -m benchmarks.unit_rates), with the
#      GPU's utilisation sampled by nvidia-smi meanwhile; then, with GPU_CHECK_DEMO_DATA=DIR (a 128 px object), the
#      demo preset on it with gsplat in the time left;
#   6. python -m benchmarks.paper_scale (the paper preset end to end) where Mitsuba is installed, in the time left;
#   7. one summary.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-${OUT:-runs/gpu-check}}
mkdir -p "$OUT"
BUDGET=${GPU_CHECK_SECONDS:-570}
START=$(date +%s)
left() { echo $((BUDGET - ($(date +%s) - START))); }
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
summary=()

SITE=$PWD
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && SITE=/tmp/site:$PWD || { echo "installing the carried wheels failed"; exit 1; }
fi
source benchmarks/gsplat_prebuilt/use.sh  # GSPLAT_PREBUILT: an earlier call's build of gsplat, loaded, not compiled
# Mitsuba cut down to what `synth` renders with (benchmarks/gpu_wheels.sh makes it; 14.6 MiB packed): the paper-scale
# object is then made here, by paper_scale and `matspray demo --preset paper`, with its cuda_ad_rgb variant
MITSUBA_ARCHIVE=${GPU_CHECK_MITSUBA:-.gpu-data/mitsuba.tar.xz}
if [ -f "$MITSUBA_ARCHIVE" ]; then
  mkdir -p /tmp/mitsuba-reduced && tar -xJf "$MITSUBA_ARCHIVE" -C /tmp/mitsuba-reduced && SITE=/tmp/mitsuba-reduced:$SITE
fi
export PYTHONPATH=$SITE
python3 -c "import torch; assert torch.cuda.is_available(), 'no CUDA GPU'; print('torch', torch.__version__, 'on', torch.cuda.get_device_name())" \
  || { echo "gpu_check: no CUDA GPU that torch sees; nothing to check"; exit 1; }

# 2. gsplat's CUDA code compiles at its first kernel call; time it once here, so that the rest finds it built
python3 - >"$OUT/gsplat_build.log" 2>&1 <<'EOF'
import time
from matspray.render.backend import resolve_backend
start = time.perf_counter()
try:
    from gsplat.cuda._backend import _C
    built = _C is not None
except Exception as exc:
    built = False
    print(f"gsplat build failed: {type(exc).__name__}: {exc}")
print(f"gsplat CUDA extension: {'built' if built else 'NOT built'} in {time.perf_counter() - start:.0f} s")
print(f"backend auto on cuda resolves to: {resolve_backend('auto', 'cuda')}")
EOF
summary+=("$(grep -h 'gsplat CUDA extension\|resolves to\|failed' "$OUT/gsplat_build.log" | paste -sd ';' -)")
gsplat_keep_build "$OUT"

# 3. the device tests on CUDA (pytest --device cuda: the on_device tests, among them the viewer's and
# the frozen views' pinned host copy, and the gsplat parity tests), after the build:
# two processes building gsplat at once break each other's build. Their tiny object needs Mitsuba; without it, one
# made elsewhere (MATSPRAY_TINY_OBJECT, see tests/conftest.py)
timeout $(( $(left) / 4 )) python3 -m pytest -q -p no:cacheprovider --device cuda -m on_device tests/test_device.py tests/test_gsplat_backend.py \
  tests/test_gsplat_parity.py tests/test_geometry_step.py tests/test_view.py 2>&1 | tee "$OUT/pytest_cuda.log"
summary+=("pytest --device cuda: $(tail -n 1 "$OUT/pytest_cuda.log")")

# 4. what a unit of work dispatches, counted on the GPU (torch's sync debug mode counts every wait for the device)
timeout 120 python3 -m benchmarks.step_cost --device cuda --json "$OUT/step_cost.json" 2>&1 | tee "$OUT/step_cost.log"
summary+=("step_cost on CUDA:" "$(grep -E '^(unit|per )' "$OUT/step_cost.log")")

# 5. with a carried `matspray synth` object (GPU_CHECK_DATA=DIR): the paper preset's per-unit rates on it, then the demo
# preset (geometry, lift, refinement of three variants, evaluation) with gsplat in the time left
RUNS=${GPU_CHECK_RUNS:-/tmp/gpu-check-runs}  # run folders stay out of OUT (too many files to bring back)
if [ -n "${GPU_CHECK_DATA:-}" ] && [ "$(left)" -gt 120 ]; then
  nvidia-smi dmon -s u -d 1 > "$OUT/dmon.log" 2>&1 &
  dmon=$!
  timeout $(( $(left) - 30 )) python3 -m benchmarks.unit_rates --data "$GPU_CHECK_DATA" --device cuda \
    --geometry-steps "${GPU_CHECK_GEOMETRY_STEPS:-7000}" --compare-eager 1000 --out "$RUNS/unit-rates" \
    --json "$OUT/unit_rates.json" 2>&1 | tr '\r' '\n' | grep -v '%|' | tee "$OUT/unit_rates.log"
  kill $dmon 2>/dev/null
  summary+=("unit rates (exit ${PIPESTATUS[0]}, 124 = out of time):" "$(grep -v '^$' "$OUT/unit_rates.log" | tail -n 8)")
  summary+=("SM utilisation while it ran (nvidia-smi dmon, mean of 1 s samples): $(awk '$1 !~ /#/ && NF > 2 {s += $2; n++} END {if (n) printf "%.0f %% over %d s", s / n, n}' "$OUT/dmon.log")")
fi
demo_run() {  # backend, seconds, variants...
  local backend=$1 limit=$2; shift 2
  # progress bars: only their last state (100%) is kept
  timeout "$limit" python3 -m benchmarks.paper_scale --preset demo --data "$GPU_CHECK_DEMO_DATA" --device cuda --backend "$backend" \
    --variants "$@" --out "$RUNS/demo-$backend" 2>&1 | tr '\r' '\n' | grep -E -v '(^|[^0-9])[0-9]{1,2}%\|' > "$OUT/demo_$backend.log"
  summary+=("demo preset on CUDA, backend $backend (exit ${PIPESTATUS[0]}, 124 = out of time):")
  summary+=("$(sed -n '/^preset /,$p' "$OUT/demo_$backend.log")")
}
if [ -n "${GPU_CHECK_DEMO_DATA:-}" ] && [ "$(left)" -gt 90 ]; then
  demo_run gsplat "$(( $(left) - 10 ))" full proj-average
fi

# 6. the paper preset, within what is left. It makes its object with Mitsuba, which the GPU image lacks: carry
# .gpu-data/mitsuba.tar.xz (above; its whole wheel, 62.5 MB, and drjit's, 5 MB, exceed the 64 MiB a call carries)
if ! python3 -c "import mitsuba" 2>/dev/null; then
  summary+=("paper_scale: not run: no Mitsuba here (carry .gpu-data/mitsuba.tar.xz: benchmarks/gpu_wheels.sh); the device tests that need a Mitsuba object skipped too")
elif [ "$(left)" -gt 60 ]; then
  timeout "$(left)" python3 -m benchmarks.paper_scale --out "$OUT/paper-scale" 2>&1 | grep -v '\r' | tee "$OUT/paper_scale.log"
  summary+=("paper_scale (exit ${PIPESTATUS[0]}, 124 = out of time):")
  summary+=("$(sed -n '/^preset /,$p' "$OUT/paper_scale.log")")
else
  summary+=("paper_scale: not run, no time left")
fi

echo
echo "==================== gpu_check summary ($(( $(date +%s) - START )) s) ===================="
printf '%s\n' "${summary[@]}"
