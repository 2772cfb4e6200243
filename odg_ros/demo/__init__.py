"""``odg demo`` without ROS: the demo world, and what is made of the node's outputs.

``odg demo`` (odg_ros/commands/demo.py) runs::

    demo_world.py        odg synth (1 scene) -> odg prepare --split all -> odg bag synth
    ros/demo_session.py  odg_node (own process) + odg replay --clock (own process) + a
                         planner stand-in that receives every output (this process), into
                         records.py's SessionRecord
    report.py            score the keyframes (mIoU, RayIoU), count, time
    picture.py           demo.png

Everything a number in the report is made of is defined here (report.py computes it):

* frames_in: camera sets the replay published (the complete sets of the bag).
* frames_out: ``~/occupancy`` grids the planner stand-in received.
* dropped: sets the node skipped, from its final ``/diagnostics``: stale sets replaced in the
  latest-wins mailbox + incomplete sets + bad-input skips (each reason separately in
  ``dropped_by_reason``). ``lost_in_transport``: grids the node published that did not arrive;
  ``unaccounted``: sets that are neither (normally 0).
* fps: grids received per second of wall time, first to last grid. ``input_fps`` is the rate
  at which sets were published, ``node_capacity_fps`` 1000 / the node's mean processing time
  per set (its stage times), i.e. what it could do if a set were always waiting.
* latency_ms_p50/p95: wall clock, from the moment the replay published the last image of a
  set (the set became complete; taken from ``/clock``, which the replay publishes just before
  each stamp) to the moment the grid of that set reached the planner stand-in: waiting in the
  mailbox + decoding + network + publishing + transport. (The node's own diagnostics latency
  is "now - image stamp" on its clock, here the bag's simulated time, which runs at ``rate``
  times wall time; it is kept in the JSON as ``node.latency_sim_ms``.)
* mIoU (camera mask) and RayIoU (+ @1/2/4 m and per class), ``metrics.score.OccScore``, over
  the keyframes whose grid was received. A grid belongs to the keyframe whose CAM_FRONT
  stamp equals the grid's header stamp (the node stamps outputs with the reference camera's
  stamp); grids of the 12 Hz sweeps between keyframes have no GT and are only counted.
"""


class DemoError(RuntimeError):
    """A demo stage failed; the message says which and why (and what to look at)."""


REFERENCE_CAMERA = "CAM_FRONT"    # the node stamps its outputs with this camera's stamp
