# Two commands do all set-up on a fresh Debian/Ubuntu machine with Python 3:
#   make demo   -> .venv, install, run the main job on the simulated sensor
#   make test   -> .venv, install test extras (+ Node packages), run the whole suite
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
DEMO_OUT ?= out/demo

REAL_DATA ?= $(if $(TACFOOT_REAL_DATA),$(TACFOOT_REAL_DATA),../shared/data)

.PHONY: native demo test install install-test install-cnn install-node clean bench models mutate memcheck layout

$(PY):
	$(PYTHON) -m venv $(VENV) || { echo "python3 -m venv failed: on Debian/Ubuntu run 'sudo apt-get install python3-venv'"; exit 1; }
	$(PIP) install --upgrade pip

# the frame core's C library (setup.py) is compiled by the install itself, next to
# its C files (an editable install); a change to them reinstalls, which recompiles
CORE_C := setup.py $(wildcard device/pi/vision/*.c)

$(VENV)/.installed: $(PY) pyproject.toml $(CORE_C)
	$(PIP) install -e '.[host,viz]'
	touch $@

# one line: which tracker runs (compiled, or numpy and why: no C compiler at install)
native: $(VENV)/.installed
	@$(PY) -m device.pi.vision.native status || true

$(VENV)/.installed-test: $(VENV)/.installed pyproject.toml $(CORE_C)
	$(PIP) install -e '.[host,test]'
	touch $@

$(VENV)/.installed-cnn: $(VENV)/.installed-test pyproject.toml $(CORE_C)
	$(PIP) install -e '.[host,test,cnn]'
	touch $@

# the real MicroPython (WebAssembly port) that the MicroPython tests run on, under Node
node_modules/.installed: package.json package-lock.json
	@command -v npm >/dev/null || { echo "npm not found: install Node.js and npm (Debian: apt-get install nodejs npm)"; exit 1; }
	npm ci --no-audit --no-fund
	touch $@

install-node: node_modules/.installed
install: $(VENV)/.installed native
install-test: $(VENV)/.installed-test node_modules/.installed native
# the optional CNN extra: the CPU build of torch (CI installs it so the CNN tests run)
install-cnn: $(VENV)/.installed-cnn

demo: $(VENV)/.installed native
	$(VENV)/bin/host demo --out $(DEMO_OUT)

test: $(VENV)/.installed-test node_modules/.installed native
	$(VENV)/bin/lint-imports --no-cache
	$(PY) -m pytest -n 2 --dist loadfile

# first the instructions per frame (valgrind's callgrind: runtime, marker pipeline and
# its stages, SimpleBlobDetector peer on roboskin/lego_train.avi as gray frames, about
# 10 minutes; out/bench/counts.json; without valgrind one line says so and they are
# skipped; Debian: apt-get install valgrind), then the real-frame tables of
# docs/BENCHMARKS.md (marker pipeline and runtime on
# roboskin/smooth.avi and concrete.avi: the authors' default spec out/specs/bench.csv,
# written from REAL_DATA), then the simulator's own timing, then what the MCAP log
# and a live Foxglove viewer cost the runtime on concrete.avi (out/bench/mcap_cost.md)
bench: $(VENV)/.installed native
	$(PY) -m host.bench.counts --real-data $(REAL_DATA) --out out/bench/counts.json --skip-without-valgrind
	$(PY) -m host.bench.specs --real-data $(REAL_DATA) --out out/specs
	$(VENV)/bin/host bench tables --data out/specs/bench.csv --doc docs/BENCHMARKS.md
	$(VENV)/bin/host bench sim --json
	$(PY) -m host.bench.mcap_cost --real-data $(REAL_DATA) --out out/bench/mcap_cost.md

# valgrind's memcheck over the runtime on 100 frames of a real clip, with the C core
# built with -g: fails if an error is in match.c or detect.c, or the core did not run
# compiled (docs/BENCHMARKS.md, "Memory safety of the C core"; about 4 minutes; not
# part of make test; Debian: apt-get install valgrind)
memcheck: $(VENV)/.installed
	$(PY) -m host.bench.memcheck --clip $(REAL_DATA)/roboskin/concrete.avi --imu $(REAL_DATA)/roboskin/concrete_gyro.npy --frames 100

# Rebuild the shipped default models in models/: the localiser (needs the real
# recordings for its real labels: REAL_DATA=path/to/data), texture from the real
# recordings, then surface, slip and pressure from simulated trials (cached in out/sim-data),
# and their fused graph (models/fused: one model call per frame on the leg).
models: $(VENV)/.installed
	$(PY) -m host.localiser --out models/localiser-roboskin --real-data $(REAL_DATA) --quiet
	$(PY) -m host.bench.shipped --out models --work out/sim-data --real-data $(REAL_DATA) --quiet
	$(PY) -m host.learn.cut models
	$(PY) -m host.learn.fuse models

# Rewrite docs/foxglove-layout.json from the code that builds it
# (device/pi/runtime/foxglove_layout.py, foxglove-sdk's foxglove.layouts; a test checks
# the file is what the code builds)
layout: $(VENV)/.installed
	$(PY) -m device.pi.runtime.foxglove_layout --out docs/foxglove-layout.json

# Mutation testing (docs/testing.md): mutmut on a private copy of the tree (it writes
# mutants/ there, never here), one mutant in ten (names ending in MUTATE_SAMPLE; '' for
# all), then the kill rate per module. About 15 minutes on 2 cores.
MUTATE_DIR ?= out/mutate
MUTATE_SAMPLE ?= 0
mutate: $(VENV)/.installed-test
	$(PIP) install -e '.[host,test,mutate]'
	rm -rf $(MUTATE_DIR) && mkdir -p $(MUTATE_DIR)
	git ls-files -z --cached --others --exclude-standard | \
	    tar --null --ignore-failed-read -T - -cf - | tar -xf - -C $(MUTATE_DIR)
	cd $(MUTATE_DIR) && $(abspath $(VENV))/bin/mutmut run --max-children 2 '*__mutmut_*$(MUTATE_SAMPLE)' || true
	cd $(MUTATE_DIR) && $(abspath $(VENV))/bin/mutmut results --all true | awk \
	    '$$2 != "not" { m = $$1; sub(/\.x(_|ǁ).*/, "", m); n[m]++; if ($$2 == "killed" || $$2 == "timeout") k[m]++ } \
	     $$2 == "survived" || $$2 == "no" { print "survived:", $$1 } \
	     END { for (m in n) printf "%-40s %4d of %4d killed (%.0f %%)\n", m, k[m], n[m], 100 * k[m] / n[m] }'

clean:
	rm -rf $(VENV) out build *.egg-info .pytest_cache .hypothesis
