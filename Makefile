# Two commands do all set-up on a fresh machine:
#   make demo   create .venv, install thermbench with the extras the demo uses (neural, onnx), run the
#               main job (the robustness benchmark) and export its models for the embedded compensator
#               (exports/benchmark/, C runtime checked)
#   make test   the system packages the tests need (tools/sysdeps.sh: apt-get as root or with sudo -n, else one
#               line naming them), create/update .venv with the dev extras (every extra the tests exercise),
#               node-opcua (npm), run the whole suite
#   make core-check  the wheel, core only (.venv-core, no torch): simulate, validate, train an MLR, export
#   make notebooks  run every notebook with full settings -> outputs/notebooks/*.ipynb (with outputs)
#   make fuzz   libFuzzer on the C runtime's model-file loader (needs clang; FUZZ_SECONDS=300)
# torch (the neural extra) is pinned to 2.13.0 through constraints.txt. On the machines this project is
# built on, pip finds that version as a local CPU-build wheel; from PyPI, Linux torch wheels are CUDA
# builds (several GB). For the CPU build elsewhere: make test TORCH_INDEX=https://download.pytorch.org/whl/cpu

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
PIP    := $(BIN)/python -m pip
export PIP_CONSTRAINT := $(CURDIR)/constraints.txt
export PIP_DISABLE_PIP_VERSION_CHECK := 1
# pip installs with --no-compile: byte-compiling every module of torch, mlflow and the rest at install
# time took about 60 s of a fresh install (measured: torch + mlflow 106 s -> 45 s); Python compiles
# what is imported, when it is first imported, and keeps it: an environment that sets
# PYTHONDONTWRITEBYTECODE would otherwise compile every import of every process again (the test suite
# runs hundreds of processes: its parallel phase went from about 510 s to 730 s)
unexport PYTHONDONTWRITEBYTECODE

# where torch comes from: empty = the package index pip is configured with; e.g. the PyTorch CPU index
TORCH_INDEX ?=
CORE_VENV   ?= .venv-core

FUZZ_SECONDS ?= 300
FUZZ_DIR     ?= build/fuzz

.PHONY: stress target-test demo test install install-dev core-check bench notebooks fuzz clean sysdeps-test sysdeps-target-test

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch first, from TORCH_INDEX when given (the CPU build), so the extras below find it installed
$(VENV)/.torch: constraints.txt | $(BIN)/python
	$(PIP) install --no-compile -c constraints.txt $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) torch
	touch $@

$(VENV)/.installed: pyproject.toml constraints.txt $(VENV)/.torch
	$(PIP) install --no-compile -c constraints.txt -e '.[neural,onnx]'
	touch $@

$(VENV)/.installed-dev: pyproject.toml constraints.txt $(VENV)/.torch
	$(PIP) install --no-compile -c constraints.txt -e '.[dev]'
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

demo: $(VENV)/.installed
	$(BIN)/thermbench benchmark
	$(BIN)/thermbench export

# the system packages a target needs (tools/system-packages.txt, the one list; the README prints it):
# nothing is run when they are installed; apt-get as root, sudo -n apt-get when that works, else one line
sysdeps-test sysdeps-target-test:
	@sh tools/sysdeps.sh $(@:sysdeps-%=%) $(SYSDEPS_LIST)

# node-opcua (npm registry), the second OPC UA stack the compensator is tested against (tests/test_node_opcua.py)
NODE_OPCUA := tests/node_opcua/node_modules/.installed
$(NODE_OPCUA): tests/node_opcua/package.json tests/node_opcua/package-lock.json
	cd tests/node_opcua && npm ci --no-audit --no-fund
	touch $@

# the wheel alone, as a release is installed: built from a copy of the source, installed without extras
# (no torch) into a fresh venv, the main commands run from an empty directory (tools/wheelcheck.py)
core-check:
	$(PYTHON) -m tools.wheelcheck --venv $(CORE_VENV)

# the real-time closed-loop tests (marker timing) run alone after the rest: on 2 cores a
# neighbouring test would steal the cycles they measure
test: sysdeps-test $(VENV)/.installed-dev $(NODE_OPCUA)
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q -m "not timing and not target"
	$(BIN)/python -m pytest -q -m timing

# the real-time tests (markers timing, realtime) STRESS_N times while STRESS_K busy loops take the cores:
# pass counts per test (tools/stress.sh; every test should pass every run)
STRESS_N ?= 10
STRESS_K ?= 2
stress: $(VENV)/.installed-dev $(NODE_OPCUA)
	PYTHON=$(BIN)/python bash tools/stress.sh $(STRESS_N) $(STRESS_K)

# the C runtime cross-compiled for the Cortex-M4F and run on QEMU's mps2-an386 (marker target);
# its system packages (cross compiler, newlib, QEMU) come from sysdeps-target-test
target-test: sysdeps-target-test $(VENV)/.installed-dev
	$(BIN)/python -m pytest -n 2 -q -m target

notebooks: $(VENV)/.installed-dev
	$(BIN)/python -m tools.nbrun

bench: $(VENV)/.installed-dev
	$(BIN)/python benchmarks/bench_simulator.py
	$(BIN)/python benchmarks/bench_identification.py
	$(BIN)/python benchmarks/bench_diagnose.py --runtime
	$(BIN)/python benchmarks/bench_export.py exports/benchmark
	$(BIN)/python benchmarks/bench_lssvm_reduced.py
	$(BIN)/python benchmarks/bench_compensator.py
	$(BIN)/python benchmarks/bench_notebooks.py
	$(BIN)/python benchmarks/bench_fl_thermal.py

# the loader and runtime under libFuzzer + ASan + UBSan; corpus grows in $(FUZZ_DIR)/corpus
fuzz:
	mkdir -p $(FUZZ_DIR)/corpus
	clang -g -O1 -fsanitize=fuzzer,address,undefined,float-cast-overflow -fno-sanitize-recover=undefined -Iembedded/include \
	  embedded/src/*.c embedded/fuzz/tb_fuzz_loader.c -o $(FUZZ_DIR)/tb_fuzz -lm
	$(FUZZ_DIR)/tb_fuzz -max_total_time=$(FUZZ_SECONDS) -max_len=65536 -print_final_stats=1 \
	  -artifact_prefix=$(FUZZ_DIR)/ $(FUZZ_DIR)/corpus embedded/fuzz/corpus

clean:
	rm -rf $(VENV) $(CORE_VENV) data/ .pytest_cache build/
