# Set-up happens on first use: a virtual environment in .venv with the package and its test tools, and the event
# engine's compiled code (numba, cached).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
OUT ?= results/default

.PHONY: run test bench stress fuzz clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@# the viewer's browser test drives Debian's Chromium; where it cannot be installed (no apt, not root) it is skipped
	-command -v chromium >/dev/null || { apt-get update -qq && apt-get install -y -qq chromium >/dev/null; } \
		|| echo "no Chromium: the viewer's browser test will be skipped"
	$(BIN)/python -c "from virtual_vehicle.run.warm import warm_up; print(f'event engine ready in {warm_up():.1f} s')"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/virtual-vehicle run --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_perf.py
	$(BIN)/python benchmarks/bench_engine.py
	$(BIN)/python benchmarks/bench_network.py
	$(BIN)/python benchmarks/bench_friction.py
	$(BIN)/python benchmarks/bench_scale.py
	$(BIN)/python benchmarks/bench_ceiling.py
	$(BIN)/python benchmarks/bench_stick_events.py
	$(BIN)/python benchmarks/bench_pairs.py
	$(BIN)/python benchmarks/bench_turntable.py
	$(BIN)/python benchmarks/bench_throughput.py
	$(BIN)/python benchmarks/bench_clocks.py
	$(BIN)/python benchmarks/bench_view.py

# the sorter's liveness over 200 generated floors (long: about a minute a seed)
stress: $(STAMP)
	$(BIN)/python benchmarks/stress_sorter.py

fuzz: $(STAMP)
	$(BIN)/python benchmarks/fuzz_sentences.py

clean:
	rm -rf $(VENV) results .pytest_cache .hypothesis
