# Two entry points: `make demo` and `make test`. Both create .venv and install what they need first: the demo the
# method with what the demo and its next steps use (Mitsuba, the viewer, export), the tests everything.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_STAMP := $(VENV)/.installed-demo
STAMP := $(VENV)/.installed
PRESET ?= demo

.PHONY: setup demo test lpips clean web

$(DEMO_STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# the pinned CPU build of torch first: an unpinned torch would pull a multi-GB CUDA build
	$(PY) -m pip install --quiet --no-compile torch==2.13.0
	$(PY) -m pip install --quiet --no-compile -e ".[demo]"
	# pip byte-compiles one file after another: instead, compileall on every core (best effort: a file that does not
	# compile, such as torch's Python 3.12 snippets, is left to compile on import), beside the compilation of backend
	# numba's kernels, which the first run would otherwise wait for (the make fails if those do not compile)
	$(PY) -m matspray.render.numba.compile & \
		$(PY) -m compileall -q -j 0 "$$($(PY) -c 'import sysconfig; print(sysconfig.get_path("purelib"))')" >/dev/null 2>&1; \
		wait $$!
	# Mitsuba's fast llvm_ad_rgb variant needs LLVM >= 16 (Debian: libllvm19); best effort, as root only.
	# Without it `matspray synth` falls back to the slower scalar_rgb variant.
	-@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! ldconfig -p | grep -q 'libLLVM.so.19'; then \
		(apt-get install -y -q libllvm19 >/dev/null 2>&1 || (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libllvm19 >/dev/null 2>&1)) \
		|| echo "note: libllvm19 not installed; Mitsuba will use its scalar_rgb variant"; fi
	touch $(DEMO_STAMP)

$(STAMP): $(DEMO_STAMP)
	$(PY) -m pip install --quiet -e ".[all,test]"
	# The Khronos glTF Validator (npm) for the export tests; best effort: without node they skip.
	-@if command -v npm >/dev/null; then npm install --silent --prefix $(VENV)/node gltf-validator >/dev/null 2>&1 \
		|| echo "note: gltf-validator not installed; the export validation test will skip"; fi
	# Headless chromium and its driver for the browser tests (viewer, glb in a glTF viewer); best effort, as root only.
	# Without them those tests skip with a reason.
	-@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! command -v chromedriver >/dev/null; then \
		(apt-get install -y -q chromium chromium-driver >/dev/null 2>&1 || (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium chromium-driver >/dev/null 2>&1)) \
		|| echo "note: chromium not installed; the browser tests will skip"; fi
	# Blender for the test of the light's orientation on import (docs/guide/export.md); best effort, as root only.
	-@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! command -v blender >/dev/null; then \
		(apt-get install -y -q blender >/dev/null 2>&1 || (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q blender >/dev/null 2>&1)) \
		|| echo "note: blender not installed; the Blender light test will skip"; fi
	# model-viewer (npm, on three.js) for the test that opens the exported glb in a standard glTF viewer; best effort.
	-@if command -v npm >/dev/null; then npm install --silent --prefix $(VENV)/node @google/model-viewer >/dev/null 2>&1 \
		|| echo "note: model-viewer not installed; the glb browser test will skip"; fi
	# CesiumJS (npm) for the test that draws --splats' tileset in a browser; best effort: without it that test skips.
	-@if command -v npm >/dev/null; then npm install --silent --prefix $(VENV)/node cesium@1.145.0 >/dev/null 2>&1 \
		|| echo "note: cesium not installed; the CesiumJS splats test will skip"; fi
	-@$(MAKE) --no-print-directory web
	touch $(STAMP)

# The script of `matspray export --web`'s page: matspray/web/src/*.js and three.js (npm) bundled by esbuild into the
# package (matspray/web/dist/, package data), so that the page fetches nothing; best effort: without node and npm,
# export --web says how to build it and its browser tests skip. A prefix of its own: model-viewer (.venv/node) pins
# another three.js as its peer.
WEB_BUNDLE := matspray/web/dist/matspray-web.js
web: $(WEB_BUNDLE)

$(WEB_BUNDLE): $(wildcard matspray/web/src/*.js)
	@if command -v npm >/dev/null; then \
		npm install --silent --prefix $(VENV)/web-build three@0.187.0 esbuild@0.28.2 >/dev/null 2>&1 \
		&& NODE_PATH=$(VENV)/web-build/node_modules $(VENV)/web-build/node_modules/.bin/esbuild matspray/web/src/main.js \
			--bundle --format=iife --minify --legal-comments=eof --target=chrome100 --log-level=warning --outfile=$@ \
		|| { echo "note: the web page's script did not build; export --web will say so"; exit 1; }; \
	else echo "note: npm not installed; export --web needs its page's script (make web)"; exit 1; fi

setup: $(STAMP)

demo: $(DEMO_STAMP)
	$(VENV)/bin/matspray demo --preset $(PRESET)

# torchvision's AlexNet weights (244 MB) into torch's cache, for LPIPS in the tables (docs/lpips.md)
lpips: $(DEMO_STAMP)
	$(PY) -m matspray.eval.lpips --download

test: $(STAMP)
	$(VENV)/bin/ruff check .
	# on every core (at most 4 workers), a test file to a worker: a file's module fixtures are made once
	$(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile

clean:
	rm -rf $(VENV) runs matspray/web/dist
