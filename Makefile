# Two commands for a newcomer: `make demo` and `make test`. Both bootstrap .venv when it is
# missing or older than pyproject.toml.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: demo reproduce test test-fast bench docs lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e '.[dev]'
	touch $(STAMP)

# The main job: the 1e5-configuration robustness sweep (resumable: rerun to continue after Ctrl-C).
demo: $(STAMP)
	$(BIN)/jaxobs sweep --out $(OUT)/sweep

reproduce: $(STAMP)
	$(BIN)/jaxobs reproduce all --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -q --durations=30

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m 'not slow and not published'

$(VENV)/.bench-installed: $(STAMP)
	$(BIN)/python -m pip install -e '.[dev,bench]'
	touch $@

bench: $(VENV)/.bench-installed
	$(BIN)/python benchmarks/kalman_throughput.py --out $(OUT)/bench
	$(BIN)/python benchmarks/sweep_throughput.py --out $(OUT)/bench
	$(BIN)/python benchmarks/mjx_rollouts.py --out $(OUT)/bench --problems
	$(BIN)/python benchmarks/tuning.py --out $(OUT)/bench --readme README.md docs/tuning-results.md
	$(BIN)/python benchmarks/dare_accuracy.py --out $(OUT)/bench
	$(BIN)/python benchmarks/care_accuracy.py --out $(OUT)/bench
	$(BIN)/python benchmarks/design_latency.py --out $(OUT)/bench
	$(BIN)/python benchmarks/nonlinear.py --out $(OUT)/bench
	$(BIN)/python benchmarks/ct_integration.py --out $(OUT)/bench
	$(BIN)/python benchmarks/parallel_in_time.py --out $(OUT)/bench
	$(BIN)/python benchmarks/estimation.py --out $(OUT)/bench
	$(BIN)/python benchmarks/estimation_breadth.py --out $(OUT)/bench
	$(BIN)/python benchmarks/learning.py --out $(OUT)/bench
	$(BIN)/python benchmarks/hgo.py --out $(OUT)/bench
	$(BIN)/python benchmarks/ct_estimation.py --out $(OUT)/bench
	$(BIN)/python benchmarks/saturated_outputs.py --out $(OUT)/bench
	$(BIN)/python benchmarks/sideslip.py --out $(OUT)/bench

# The documentation site (MkDocs, Material theme, API reference from the docstrings) into site/; --strict: any
# warning (a broken link or cross-reference, an example that no longer exists) fails the build.
# NO_MKDOCS_2_WARNING silences a banner that mkdocs-material prints on every build.
$(VENV)/.docs-installed: $(STAMP)
	$(BIN)/python -m pip install -e '.[docs]'
	touch $@

docs: $(VENV)/.docs-installed
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# ruff's rules (pyproject.toml) and its formatting, checked, never applied
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) $(OUT) site .pytest_cache
