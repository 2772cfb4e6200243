"""The ODG network (ROS-free). See odg.py for the entry point."""
from .odg import ODG
from .outputs import LayerOutput, ODGOutput

__all__ = ["ODG", "ODGOutput", "LayerOutput"]
