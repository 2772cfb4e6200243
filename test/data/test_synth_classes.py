"""Scene classes of the synthetic world (data/synth/city/scene.py): quiet, normal and dense
traffic really differ in road users, the open road has no crossing roads and no city blocks,
and the held-out worlds of each class are pinned (seed and what they hold)."""
import collections

import pytest

from odg_ros.data.synth.city import HELD_OUT, SceneKind
from odg_ros.data.synth.generate import scene_world

SECONDS = 4.0           # the held-out worlds' length (docs/results/query_budget.md)


def road_users(world) -> dict[str, int]:
    counts = collections.Counter(thing.kind for thing in world.things)
    return {kind: counts[kind] for kind in ("vehicle", "cycle", "pedestrian")}


def test_traffic_classes_differ_on_the_same_roads():
    """Same seed, same roads: quiet < normal < dense in vehicles and in pedestrians."""
    for seed in (9101, 9102):
        users = {traffic: road_users(scene_world(seed, 0, SECONDS, SceneKind(traffic)))
                 for traffic in ("quiet", "normal", "dense")}
        for kind in ("vehicle", "pedestrian"):
            quiet, normal, dense = (users[t][kind] for t in ("quiet", "normal", "dense"))
            assert 1.5 * quiet < normal < dense, (seed, kind, users)


def test_the_open_road_has_one_road_and_few_people():
    city = scene_world(9104, 0, SECONDS, SceneKind("normal"))
    road = scene_world(9104, 0, SECONDS, SceneKind("normal", "open-road"))
    assert road.name == city.name and road.duration == city.duration
    assert sum(road_users(road).values()) < 0.3 * sum(road_users(city).values())
    assert road_users(road)["pedestrian"] < 0.1 * road_users(city)["pedestrian"]


def test_the_held_out_worlds_are_pinned():
    """What each held-out world holds: a change of the generator or of a seed shows here."""
    held = {name: road_users(scene_world(seed, 0, SECONDS, kind))
            for name, (seed, kind) in HELD_OUT.items()}
    assert held == {"city-quiet": {"vehicle": 72, "cycle": 10, "pedestrian": 49},
                    "city-normal": {"vehicle": 238, "cycle": 28, "pedestrian": 149},
                    "city-dense": {"vehicle": 322, "cycle": 45, "pedestrian": 336},
                    "open-road": {"vehicle": 29, "cycle": 3, "pedestrian": 5}}


def test_an_unknown_class_is_refused():
    with pytest.raises(ValueError, match="traffic 'busy': expected one of quiet, normal, dense"):
        SceneKind("busy")
    with pytest.raises(ValueError, match="roads 'highway'"):
        SceneKind("quiet", "highway")
    assert SceneKind().description == "city"
    assert SceneKind("dense", "open-road").description == "open road, dense traffic"
