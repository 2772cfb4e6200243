#!/usr/bin/env bash
# Builds the odg_ros_msgs interface package (msg/) with plain CMake against the ROS 2 PyPI
# wheels and installs it into the virtualenv given as $1 (default .venv), so that
# `from odg_ros_msgs.msg import SemanticVoxelGrid` works in every process of that venv's python.
#
# Layout it installs into (the same one the ROS wheels use):
#   $VENV/lib/libodg_ros_msgs__*.so                       C/C++ type support libraries
#   $VENV/lib/python3.X/site-packages/odg_ros_msgs/       the Python message package
#   $VENV/share/odg_ros_msgs/, $VENV/share/ament_index/   CMake config + ament index entry
# No environment variable is needed at run time: the wheels' ros_wheels_bootstrapper (.pth)
# re-executes python with $VENV/lib on LD_LIBRARY_PATH, where the libraries above land.
#
# It also builds tools/ros_shims/tf2_msgs (TFMessage only) when the venv has no tf2_msgs: PyPI
# has no wheel for it, and /tf replay and the node need it (see tools/ros_shims/README.md).
#
# Idempotent: skips a package whose install was built from the same inputs (a stamp file).
# On a ROS 2 install use colcon instead (see msg/README.md).
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$(cd "${1:-$root/.venv}" && pwd)"
py="$venv/bin/python"

for tool in cmake cc c++; do
  command -v "$tool" >/dev/null || { echo "build_msgs: '$tool' not found (apt-get install cmake g++)" >&2; exit 1; }
done

# The wheels were built in a manylinux container and hard-code its Python and NumPy include
# directories in their exported CMake targets; point them at this machine's (idempotent).
py_include="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
np_include="$("$py" -c 'import numpy; print(numpy.get_include())')"
[[ -f "$py_include/Python.h" ]] || { echo "build_msgs: Python.h not found in $py_include (install python3-dev)" >&2; exit 1; }
"$py" - "$venv" "$py_include" "$np_include" <<'EOF'
import pathlib
import re
import sys

venv, py_include, np_include = sys.argv[1:]
for path in pathlib.Path(venv, "share").glob("*/cmake/*Export*.cmake"):
    text = path.read_text()
    fixed = re.sub(r"/opt/python/cp\d+-cp\d+/include/python3\.\d+", py_include, text)
    fixed = re.sub(r'[^;"]*/site-packages/numpy/_?core/include', np_include, fixed)
    if fixed != text:
        path.write_text(fixed)
        print(f"build_msgs: fixed include paths in {path.name}")
EOF

# build_package NAME SOURCE_DIR IMPORT_CHECK: configure, build and install one interface package
# into the venv unless the stamp says it was built from the same inputs.
build_package() {
  local name="$1" src="$2" check="$3"
  local build="$venv/build/$name" stamp="$venv/share/$name/.odg_build_stamp" hash
  hash="$( (cat "$root/tools/build_msgs.sh" "$src/CMakeLists.txt" "$src/package.xml" "$src"/msg/*.msg; \
            "$py" -c 'import sys; print(sys.version)') | sha256sum | cut -d' ' -f1)"
  if [[ -f "$stamp" && "$(cat "$stamp")" == "$hash" ]] && "$py" -c "$check" 2>/dev/null; then
    echo "build_msgs: $name is up to date in $venv"
    return 0
  fi
  echo "build_msgs: building $name into $venv"
  mkdir -p "$build"
  AMENT_PREFIX_PATH="$venv" cmake -S "$src" -B "$build" \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$venv" \
    -DCMAKE_INSTALL_PREFIX="$venv" \
    -DPython3_EXECUTABLE="$py" \
    -DBUILD_TESTING=OFF > "$build.configure.log" 2>&1 \
    || { tail -40 "$build.configure.log" >&2; return 1; }
  cmake --build "$build" -j "$(nproc)" > "$build.build.log" 2>&1 \
    || { grep -E -B2 -A8 'error|Error' "$build.build.log" | tail -60 >&2; return 1; }
  cmake --install "$build" > "$build.install.log" 2>&1 \
    || { tail -40 "$build.install.log" >&2; return 1; }
  "$py" -c "$check" || { echo "build_msgs: built $name, but it does not import" >&2; return 1; }
  echo "$hash" > "$stamp"
  echo "build_msgs: $name installed in $venv"
}

# PyPI has no tf2_msgs wheel; build the TFMessage-only shim unless a real one is there.
if [[ -f "$venv/share/tf2_msgs/.odg_build_stamp" ]] || ! "$py" -c "import tf2_msgs" 2>/dev/null; then
  build_package tf2_msgs "$root/tools/ros_shims/tf2_msgs" "from tf2_msgs.msg import TFMessage"
fi
build_package odg_ros_msgs "$root/msg" \
  "from odg_ros_msgs.msg import SemanticVoxelGrid, DynamicObject, DynamicObjectArray"
