# GeoPose: set-up, demo and tests. Everything installs into .venv/ in this folder.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-slow fuzz bench clean chromium view

# Slicer 5.8's Python (3.9) with the packages it ships at its versions, for Testing/Python/test_python39.py:
# .venv-py39 adds GeoPose's requirements (the torch-free registration runs there), .venv-py39-slicer58
# holds Slicer's packages only (the module's first-install planning runs there, pip --dry-run).
PY39 ?= $(firstword $(wildcard $(shell pyenv root 2>/dev/null)/versions/3.9*/bin/python3.9) python3.9)
VENV39 := .venv-py39
VENV39_SLICER := .venv-py39-slicer58

# Requirements: Logic/geopose/requirements/ (pyproject.toml reads them). The exact torch==2.13.0 installed first is
# this set-up's PyTorch, the release of the torch floor there (torch.txt >=2.13; Testing/Python/test_dependencies.py
# checks they agree).
$(BIN)/geopose: pyproject.toml $(wildcard Logic/geopose/requirements/*.txt)
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[torch,test,web]"
	touch $@

setup: $(BIN)/geopose

# Debian's Chromium for the browser test (Testing/Python/test_web.py, Playwright drives it; Playwright's own
# browser download is not used). Installed with apt when missing and run as root; otherwise the test skips and says so.
chromium:
	@if command -v chromium >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium libegl1 libgl1-mesa-dri >/dev/null; \
	else echo "no chromium and not root with apt: the browser test will be skipped"; fi

# Built when a Python 3.9 is found; without one, test_python39 skips and says so.
$(VENV39)/.installed: Testing/Python39/requirements.txt Testing/Python39/slicer58.txt Logic/geopose/requirements/slicer.txt
	@if command -v $(PY39) >/dev/null 2>&1; then \
		$(PY39) -m venv $(VENV39) && $(VENV39)/bin/python -m pip install -q -r Testing/Python39/requirements.txt && touch $@; \
	else echo "no Python 3.9 found: the Slicer 5.8 (Python 3.9) check will be skipped"; fi

$(VENV39_SLICER)/.installed: Testing/Python39/slicer58.txt
	@if command -v $(PY39) >/dev/null 2>&1; then \
		$(PY39) -m venv $(VENV39_SLICER) && $(VENV39_SLICER)/bin/python -m pip install -q -r Testing/Python39/slicer58.txt && touch $@; \
	else echo "no Python 3.9 found: the Slicer 5.8 install-planning check will be skipped"; fi

demo: setup
	$(BIN)/geopose demo --out demo_out

# The browser app on http://127.0.0.1:8080/ (README "In the browser").
view: setup
	$(BIN)/geopose view

test: setup $(VENV39)/.installed $(VENV39_SLICER)/.installed chromium
	$(BIN)/python -m pytest -q

test-slow: setup chromium
	GEOPOSE_SLOW=1 $(BIN)/python -m pytest -q

# Input fuzz suite: 10,000 seeded mutations of every input kind and 1,000 CLI-level situations (docs/fuzz.md); the default
# test run does 600 of them (Testing/Python/test_fuzz.py).
FUZZ_CASES ?= 10000
fuzz: setup
	nice -n 10 $(BIN)/python Testing/fuzz/run.py --cases $(FUZZ_CASES) --seed 0 --workers 2 --doc docs/fuzz.md

clean:
	rm -rf $(VENV) $(VENV39) $(VENV39_SLICER) demo_out demo_out_case

# Renderer benchmark against DiffDRR 0.6.1, which lives in its own environment
# (.venv-diffdrr, built once by benchmarks/setup_diffdrr_env.sh). Tables go to
# docs/renderer_benchmark.md (+ docs/renderer_benchmark_<device>.json); CUDA is
# benchmarked too when torch sees a GPU.
DIFFDRR_PY := .venv-diffdrr/bin/python
.PHONY: bench-renderer bench-conventions

$(DIFFDRR_PY):
	benchmarks/setup_diffdrr_env.sh

bench-renderer: | $(DIFFDRR_PY)
	$(DIFFDRR_PY) benchmarks/bench_renderer.py --threads 2 --device cpu --doc docs/renderer_benchmark.md
	if $(DIFFDRR_PY) -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then \
		$(DIFFDRR_PY) benchmarks/bench_renderer.py --device cuda --doc docs/renderer_benchmark.md; fi

# Left and right on real data (docs/conventions.md, section 7): figure and numbers
# (docs/conventions_isoposes.png, docs/conventions_check.json), then the DiffDRR-on-NIfTI checks.
bench-conventions: | $(DIFFDRR_PY)
	$(DIFFDRR_PY) benchmarks/bench_conventions.py --out docs
	$(DIFFDRR_PY) -m pytest -q Testing/Python/test_conventions_diffdrr.py Testing/Python/test_render_diffdrr.py
