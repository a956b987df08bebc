# Two commands on a fresh machine: `make demo` and `make test` (each sets up .venv first).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench-quick bench-compare-quick bench-view-quick bench-scale-quick soak-quick clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev,refiner,view,test-browser,distributed]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/bokehray demo -o bokehray-demo

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q

# the structure of docs/architecture.md (import direction, no cycles, kernels pure) and a lint pass
lint: $(STAMP)
	$(BIN)/ruff check src kernels refiner benchmarks research tests
	$(BIN)/lint-imports
	@! git grep -nE '^(<<<<<<<|>>>>>>>)( |$$)' -- . || { echo "lint: unresolved merge-conflict markers (above)"; exit 1; }

# the preview's speed beside the committed baseline (benchmarks/results/baseline.json): REGRESSION marks a figure
# 15 % worse; a print, never a failure (CI may run on a busy machine)
bench-quick: $(STAMP)
	$(BIN)/python benchmarks/renderer/bench_guard.py
	$(BIN)/python benchmarks/renderer/bench_preview.py --quick
	$(BIN)/python benchmarks/renderer/bench_bokeh_shape.py --quick

# run time against error, bokehray levels and peers side by side (docs/benchmarks.md); peers that
# are not installed are skipped with a one-line message
bench-compare-quick: $(STAMP)
	$(BIN)/bokehray bench --quick --out out/bench

# live-preview latency of bokehray view (docs/view.md); the full run writes benchmarks/results and docs/img
bench-view-quick: $(STAMP)
	$(BIN)/python benchmarks/page/bench_view.py --quick --out out/bench-view
# local pool vs Dask with 2 workers: engine cost per task, scenes/min, MP/s (docs/scale.md)
bench-scale-quick: $(STAMP)
	$(BIN)/python benchmarks/scale/bench_scale.py --quick --out out/bench-scale --plots out/bench-scale

soak-quick: $(STAMP)
	$(BIN)/python benchmarks/robustness/soak.py --cases 300 --seed 1

clean:
	rm -rf $(VENV) bokehray-demo .pytest_cache .hypothesis
