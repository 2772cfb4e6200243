"""Procedural layout of one scene in the city frame; ``build_world`` returns a World.

A grid of roads (lanes, medians, parking lanes, sidewalks, crosswalks, markings:
road_grid.py, roads.py), blocks (buildings, parks, parking lots, building sites) and street
furniture (furniture.py), and the traffic: the ego's route (ego.py), vehicles, cyclists,
parked cars and construction zones (traffic.py) and pedestrians (pedestrians.py), kept
free of collisions (collisions.py). scene.py builds one scene from these sections, of a
``SceneKind``: quiet, normal or dense traffic, in the city or on an open road.
"""
from .scene import HELD_OUT, ROADS, TRAFFIC, SceneKind, build_world

__all__ = ["HELD_OUT", "ROADS", "TRAFFIC", "SceneKind", "build_world"]
