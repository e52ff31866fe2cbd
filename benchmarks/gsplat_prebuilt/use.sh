# Sourced by the GPU scripts (gpu_check.sh, gpu_units.sh) after the carried wheels are installed, with SITE their
# PYTHONPATH so far:
#   - with GSPLAT_PREBUILT=FILE (an earlier call's gsplat_cuda.so.xz, carried), gsplat's CUDA extension is loaded from
#     it instead of compiled (sitecustomize.py here; SITE gains its folder);
#   - `gsplat_keep_build OUT`, after gsplat has built, writes that build to OUT/gsplat_cuda.so.xz for the next call.
if [ -n "${GSPLAT_PREBUILT:-}" ] && [ -f "$GSPLAT_PREBUILT" ]; then
  mkdir -p /tmp/gsplat-prebuilt && xz -dc "$GSPLAT_PREBUILT" >/tmp/gsplat-prebuilt/gsplat_cuda.so \
    && cp "$(dirname "${BASH_SOURCE[0]}")/sitecustomize.py" /tmp/gsplat-prebuilt/ \
    && export GSPLAT_PREBUILT_SO=/tmp/gsplat-prebuilt/gsplat_cuda.so && SITE=/tmp/gsplat-prebuilt:$SITE
fi

gsplat_keep_build() {  # OUT
  [ -n "${GSPLAT_PREBUILT_SO:-}" ] && return 0  # loaded from a carried build: nothing new to keep
  local root=${TORCH_EXTENSIONS_DIR:-$HOME/.cache/torch_extensions} built
  built=$(ls "$root"/gsplat_cuda/gsplat_cuda.so "$root"/*/gsplat_cuda/gsplat_cuda.so 2>/dev/null | head -n 1)
  if [ -n "$built" ]; then
    xz -T0 -1 -c "$built" >"$1/gsplat_cuda.so.xz" && echo "gsplat's build kept in $1/gsplat_cuda.so.xz (GSPLAT_PREBUILT)"
  fi
}
