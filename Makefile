# One entry point for set-up, the main job, the tests and the benchmarks.
#   make sim    set up, then run the headless simulated calibration and write its report
#   make test   set up, then run the tests
#   make bench  set up, then run the benchmarks
#   make colcon set up (with colcon), then build and test both packages in a temporary colcon workspace
# Set-up is idempotent: each step leaves a stamp in .venv/ and runs again only when its inputs change.
SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := setup

VENV := $(CURDIR)/.venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp
OUT ?= reports/sim-cell
PYTEST_ARGS ?=
SUDO := $(if $(filter 0,$(shell id -u)),,sudo)
# pip prints a warning for every package its extra local indexes do not hold; keep the log readable.
QUIET_PIP := sed '/is ignored: it is neither a file nor a directory/d'

# Small matrices under two busy cores: threaded BLAS only adds jitter (see docs/benchmarks.md).
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: setup sim test bench colcon clean
setup: $(STAMP)/package

$(PY):
	python3 -m venv $(VENV)

$(STAMP)/apt: | $(PY)
	mkdir -p $(STAMP)
	dpkg -s libusb-1.0-0 >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0; }
	touch $@

$(STAMP)/requirements: requirements.txt $(STAMP)/apt
	$(PY) -m pip install -q -r requirements.txt 2>&1 | $(QUIET_PIP)
	$(PY) -m pip check >/dev/null
	touch $@

# The interface package is built with CMake from the ROS wheels and installed into the venv prefix,
# where its Python module is importable without sourcing anything.
$(STAMP)/msgs: $(STAMP)/requirements $(shell find msg_defs -type f)
	rm -rf build/msg_defs
	mkdir -p build
	AMENT_PREFIX_PATH=$(VENV) CMAKE_PREFIX_PATH=$(VENV) cmake -S msg_defs -B build/msg_defs \
	  -DCMAKE_INSTALL_PREFIX=$(VENV) -DPython3_EXECUTABLE=$(PY) -DBUILD_TESTING=OFF \
	  -DCMAKE_BUILD_TYPE=Release > build/msg_defs.log 2>&1 || { tail -40 build/msg_defs.log; exit 1; }
	cmake --build build/msg_defs -j2 >> build/msg_defs.log 2>&1 || { tail -40 build/msg_defs.log; exit 1; }
	cmake --install build/msg_defs >> build/msg_defs.log 2>&1
	cd /tmp && $(PY) -c "from gls_calibration_msgs.srv import Calibrate, CorrectSetpoints"
	touch $@

# tf2_msgs/msg/TFMessage (the type of /tf and /tf_static) where no tf2_msgs is importable: the pip set-up
# has none. Built the way msg_defs/ is; a tf2_msgs from elsewhere (a ROS installation) is left alone.
# The stamp says which: "built" (ours, rebuilt when msg_defs_tf2/ changes) or "present" (not ours).
$(STAMP)/tf2_msgs: $(STAMP)/requirements $(shell find msg_defs_tf2 -type f) msg_defs/cmake/gls_drop_missing_include_dirs.cmake
	if { test -f $@ && grep -qx built $@; } || ! (cd /tmp && $(PY) -c "import tf2_msgs" 2>/dev/null); then \
	  rm -rf build/msg_defs_tf2 && mkdir -p build && \
	  { AMENT_PREFIX_PATH=$(VENV) CMAKE_PREFIX_PATH=$(VENV) cmake -S msg_defs_tf2 -B build/msg_defs_tf2 \
	      -DCMAKE_INSTALL_PREFIX=$(VENV) -DPython3_EXECUTABLE=$(PY) -DBUILD_TESTING=OFF \
	      -DCMAKE_BUILD_TYPE=Release > build/msg_defs_tf2.log 2>&1 \
	    && cmake --build build/msg_defs_tf2 -j2 >> build/msg_defs_tf2.log 2>&1 \
	    && cmake --install build/msg_defs_tf2 >> build/msg_defs_tf2.log 2>&1; } \
	  || { tail -40 build/msg_defs_tf2.log; exit 1; }; \
	  (cd /tmp && $(PY) -c "from tf2_msgs.msg import TFMessage"); \
	  echo built > $@; \
	else echo present > $@; fi

$(STAMP)/package: $(STAMP)/msgs $(STAMP)/tf2_msgs setup.py setup.cfg package.xml
	$(PY) -m pip install -q --no-deps --no-build-isolation -e . 2>&1 | $(QUIET_PIP)
	touch $@

# colcon from PyPI, into the same venv: its ament_python build runs setup.py with colcon's interpreter,
# which must see setuptools and the ROS wheels.
$(STAMP)/colcon: requirements-colcon.txt $(STAMP)/package
	$(PY) -m pip install -q -r requirements-colcon.txt 2>&1 | $(QUIET_PIP)
	$(PY) -m pip check >/dev/null
	touch $@

colcon: $(STAMP)/colcon
	.ci/colcon_workspace

sim: setup
	$(VENV)/bin/gls-sim-cell --out $(OUT)

test: setup
	$(PY) -m pytest $(PYTEST_ARGS)

bench: setup
	for script in benchmarks/bench_*.py; do echo "== $$script"; $(PY) $$script; done

clean:
	rm -rf build $(VENV)
