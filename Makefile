# rkgnn_ros: one command sets a fresh machine up, one runs the tests, one the main job.
#   make test    set up (if needed), build with colcon, run the whole test suite
#   make test-fast  the same without the tests marked slow (test/conftest.py): minutes
#   (make build also compiles the numba kernels into their cache: seconds once cached)
#   make demo    set up (if needed), run sim_arm + identifier, write a figure
#   make paper   reproduce the paper's three cases (figures + table in bench/results)
#   make bench   benchmarks (bench/results)
#   make soak    30-minute soak run; make killtest: SIGKILL during saves, 50 times
SHELL := /bin/bash
.SHELLFLAGS := -o pipefail -c
PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.requirements-$(shell sha1sum requirements.txt | cut -c1-12)
# every run of the tests and the demo gets its own DDS domain, so runs never hear each other
export ROS_DOMAIN_ID ?= $(shell echo $$(( ($$$$ % 200) + 20 )))
export RMW_IMPLEMENTATION ?= rmw_fastrtps_cpp
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: setup build test test-fast demo paper bench soak killtest lint clean

setup: $(STAMP) build

$(STAMP): requirements.txt
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	@touch $(VENV)/COLCON_IGNORE
	@echo 'installing the pinned requirements into $(VENV) (first run: about a minute)'
	$(VPY) -m pip install -q --disable-pip-version-check -r requirements.txt 2>&1 | \
		{ grep -v '^WARNING: Location' || true; }
	@rm -f $(VENV)/.requirements-* && touch $@

build: $(STAMP)
	@$(VENV)/bin/colcon --log-base log build --symlink-install --base-paths . \
		--event-handlers console_cohesion- status- summary+ 2>&1 | grep -v '^$$' || \
		{ echo 'colcon build failed: see log/latest_build'; exit 1; }
	@source install/setup.bash && $(VPY) tools/precompile.py | tail -n 1 || \
		echo 'precompile failed: the first identifier run compiles the kernels itself'

test: setup
	@source install/setup.bash && $(VENV)/bin/colcon --log-base log test --base-paths . \
		--event-handlers console_direct+ status- summary- \
		--pytest-args -p no:cacheprovider $(PYTEST_ARGS)
	@$(VENV)/bin/colcon --log-base log test-result --test-result-base build/rkgnn_ros --verbose

test-fast: setup
	@source install/setup.bash && $(VPY) -m pytest -q -p no:cacheprovider -m 'not slow' test/ \
		$(PYTEST_ARGS)

demo: setup
	@source install/setup.bash && $(VPY) tools/demo.py $(DEMO_ARGS)

paper: setup
	@source install/setup.bash && $(VPY) tools/paper.py $(PAPER_ARGS)

bench: setup
	@source install/setup.bash && $(VPY) bench/run_all.py $(BENCH_ARGS)

soak: setup
	@source install/setup.bash && $(VPY) bench/soak.py $(SOAK_ARGS)

killtest: setup
	@source install/setup.bash && $(VPY) bench/killtest.py $(KILLTEST_ARGS)

clean:
	rm -rf build install log
