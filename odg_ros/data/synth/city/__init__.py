"""Procedural layout of one scene; ``build_world`` returns a World."""
from odg_ros.data.synth.city.furniture import build_world

__all__ = ["build_world"]
