# curvimesh — every target works on a fresh clone: it makes .venv and installs into it.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: demo test lint bench sample-runs robustness convergence clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	@mkdir -p out
	$(BIN)/curvimesh check-metric metrics/toy.yaml
	$(BIN)/curvimesh adapt --metric metrics/toy.yaml -o out/toy.msh --stats out/toy-stats.json
	$(BIN)/curvimesh report out/toy.msh --metric metrics/toy.yaml --plot out/toy.png

test: $(STAMP)
	$(BIN)/pytest -q

lint: $(STAMP)
	$(BIN)/ruff check curvimesh tests bench
	$(BIN)/ruff format --check curvimesh tests bench

bench: $(STAMP)
	$(BIN)/python bench/run.py

sample-runs: $(STAMP)
	$(BIN)/curvimesh batch metrics/*.yaml --out-dir sample_runs --jobs 2 --readme
	$(BIN)/python bench/ablation.py metrics/*.yaml --out sample_runs --jobs 2

robustness: $(STAMP)
	$(BIN)/python bench/robustness.py

convergence: $(STAMP)
	$(BIN)/python bench/convergence.py --out sample_runs --vertices 500 1000 2000 4000 8000 16000 32000 50000

clean:
	rm -rf $(VENV) out .pytest_cache
