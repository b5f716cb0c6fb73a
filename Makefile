# GeoPose: set-up, demo and tests. Everything installs into .venv/ in this folder.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-slow fuzz bench clean

$(BIN)/geopose: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $@

setup: $(BIN)/geopose

demo: setup
	$(BIN)/geopose demo --out demo_out

test: setup
	$(BIN)/python -m pytest -q

test-slow: setup
	GEOPOSE_SLOW=1 $(BIN)/python -m pytest -q

# Input fuzz suite: 10,000 seeded mutations of every input kind (docs/fuzz.md); the default
# test run does 600 of them (Testing/Python/test_fuzz.py).
FUZZ_CASES ?= 10000
fuzz: setup
	nice -n 10 $(BIN)/python Testing/fuzz/run.py --cases $(FUZZ_CASES) --seed 0 --workers 2 --doc docs/fuzz.md

clean:
	rm -rf $(VENV) demo_out

# Renderer benchmark against DiffDRR 0.6.1, which lives in its own environment
# (.venv-diffdrr, built once by benchmarks/setup_diffdrr_env.sh). Tables go to
# docs/renderer_benchmark.md (+ docs/renderer_benchmark_<device>.json); CUDA is
# benchmarked too when torch sees a GPU.
DIFFDRR_PY := .venv-diffdrr/bin/python
.PHONY: bench-renderer

$(DIFFDRR_PY):
	benchmarks/setup_diffdrr_env.sh

bench-renderer: | $(DIFFDRR_PY)
	$(DIFFDRR_PY) benchmarks/bench_renderer.py --threads 2 --device cpu --doc docs/renderer_benchmark.md
	if $(DIFFDRR_PY) -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then \
		$(DIFFDRR_PY) benchmarks/bench_renderer.py --device cuda --doc docs/renderer_benchmark.md; fi
