# brace_control: `make demo` runs the lumbar brace on the simulated CAN bus,
# `make test` runs the whole test suite. Both create .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
DEVICE ?= lumbar_brace
# position: the bundled exercise; interaction: zero-torque mode and a wrench goal (issue 14)
MODE   ?= position

# DDS discovery stays on this machine unless the caller says otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export MPLBACKEND ?= Agg

.PHONY: venv demo test bench colcon clean

venv: $(VENV)/.installed

# The package is byte-compiled at install, as pip compiles what it installs: with
# PYTHONDONTWRITEBYTECODE set (this machine sets it) every process would otherwise compile
# every module it imports, each time (a node's start: 0.40 -> 0.30 s of CPU; bench/RESULTS.md,
# "sixth session").
$(VENV)/.installed: requirements.txt setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) -m compileall -q brace_control
	touch $@

demo: venv
	$(PY) -m brace_control.demo --device $(DEVICE) --mode $(MODE) --out demo_output

# pytest exits 5 when it collected no test: that is a failure here, said out loud.
# Three pytest-xdist workers, a whole file each at a time (--dist loadfile: a module's stack
# fixtures stay on one worker), each on its own ROS domain (test/conftest.py). Each stack's
# control cycle runs in a real-time process of its own (issue 27), and the suite keeps two
# cores busy: on a slower day of this host four workers took 7:11-7:43 of pytest and failed
# 4 runs of 4 on starved stacks (load average 13), three took 6:13-6:50 (bench/RESULTS.md,
# "ninth session"; four were faster on the sixth session's host, 4:45 against 5:30).
# --no-loadscope-reorder: the files go out in test/conftest.py's order, the longest first
# (xdist's own order, the most tests first, left the few-test bring-up files for the end).
# TEST_WORKERS=0 runs everything in one process; timings: bench/RESULTS.md "Test suite time".
TEST_WORKERS ?= 3
test: venv
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests" >&2; fi; \
	exit $$rc

# every benchmark script; numbers and the commands that made them: bench/RESULTS.md
bench: venv
	for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

colcon: venv
	$(VENV)/bin/colcon build --base-paths . --build-base build --install-base install

clean:
	rm -rf build install log demo_output .pytest_cache
