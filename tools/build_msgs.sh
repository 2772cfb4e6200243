#!/usr/bin/env bash
# Builds the odg_ros_msgs interface package into the virtualenv given as $1 (filled in by the
# messages work, issue 5).
set -euo pipefail
echo "build_msgs: nothing to build yet"
