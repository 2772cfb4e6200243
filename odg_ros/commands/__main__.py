"""``python -m odg_ros.commands``: the ``odg`` command (as torchrun's ``-m`` needs it)."""
import sys

from . import main

sys.exit(main())
