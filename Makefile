# Two entry points that do all the set-up on a fresh machine (Python 3.11, pip, make):
#   make demo   sets up .venv and runs the main job on the embedded default scene
#   make test   sets up .venv and runs the test suite
# TORCH_SPEC chooses the torch to install when the venv has no torch $(TORCH_VERSION) (default:
# whatever the installer finds for the pin; on this build machine a local CPU wheel. Elsewhere pass
# the index: TORCH_SPEC="torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu" or .../cu126).
# Packages are installed by uv (pinned, itself installed into the venv by pip): the same versions
# pip resolves, in about 70 s instead of pip's ~120 s here (empty uv cache), seconds for the test tools.

PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
TORCH_VERSION := 2.13.0
TORCH_SPEC ?= torch==$(TORCH_VERSION)
STAMP  := $(VENV)/.installed
TEST_STAMP := $(VENV)/.installed-test
UV_VERSION := 0.13.9
UV      = $(VENV)/bin/uv pip install --quiet --compile-bytecode --python $(PY) $(foreach d,$(FIND_LINKS),--find-links $(d))
# uv compiles no bytecode by default, and where PYTHONDONTWRITEBYTECODE is set (as on this build
# machine) Python then compiles torch on every import (+7 s a process): every install passes
# --compile-bytecode, which compiles what that install put in the venv (not what was there).
# uv reads no pip configuration: pass on pip's local wheel folders (--find-links; this machine's
# CPU torch lies in one). Lazily expanded, so only the install recipes ask pip.
FIND_LINKS ?= $(or $(PIP_FIND_LINKS),$(shell $(PYTHON) -m pip config get global.find-links 2>/dev/null))

.PHONY: setup test demo addon clean-venv

setup: $(STAMP) $(TEST_STAMP)

# What the pipeline needs (the demo's set-up): torch, the package with rendering, LPIPS weights.
$(STAMP): pyproject.toml Makefile
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (Python 3.11 is required)"; exit 1; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@test -x $(VENV)/bin/uv || $(PY) -m pip install --quiet uv==$(UV_VERSION)
	@# Keep an installed torch of the pinned version (CPU or CUDA build); otherwise install
	@# TORCH_SPEC first, so the installer never resolves torch itself (that would pull CUDA packages).
	@$(PY) -c "import sys, torch; sys.exit(torch.__version__.split('+')[0] != '$(TORCH_VERSION)')" >/dev/null 2>&1 \
		|| $(UV) $(TORCH_SPEC)
	$(UV) -e ".[render]"
	@# LPIPS AlexNet v0.1 weights for offline evaluation, fetched and converted once (idempotent).
	$(PY) -m benchgen.score.lpips install
	@touch $(STAMP)

# What the tests need besides (30 s of the set-up: ray, hypothesis, pytest): `make demo` skips it.
$(TEST_STAMP): $(STAMP)
	$(UV) -e ".[render,test]"
	@# Reference for the LPIPS tests: lpips' shipped heads only. --no-deps because its declared
	@# torchvision would pull a CUDA torch; nothing imports it outside tests.
	$(UV) --no-deps lpips==0.1.4
	@touch $(TEST_STAMP)

test: $(TEST_STAMP)
	$(PY) -m pytest -q

demo: $(STAMP)
	$(VENV)/bin/osn demo

clean-venv:
	rm -rf $(VENV)

# Installable Blender extension zip (Blender 4.2+ / 5.0) in dist/.
addon: $(STAMP)
	$(PY) -m osn.export.addon_build --out dist
