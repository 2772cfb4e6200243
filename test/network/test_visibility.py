"""Visibility (network/visibility.py): which voxels the cameras observe, from a label grid and
a missed-occupancy hazard.

Hard cases with known answers (the road to the horizon, what lies under it, a wall, a pole,
the image bounds, broken geometry, a band of uncertain space), no host read inside it, the
step's test against the optical depths the hazard is fitted on, and agreement with a
synthetic world's own mask_camera (ray-cast against the true geometry,
data/synth/occupancy.py)."""
import numpy as np
import pytest
import torch

from odg_ros.geometry import invert_transform
from odg_ros.network.visibility import Visibility, image_bounds
from odg_ros.preprocess import adjust_intrinsics

FREE = 17
SHAPE = (200, 200, 16)
PC_RANGE = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)
INPUT_HW = (128, 352)
CAMERA_HEIGHT = 1.6


def centre(index, axis):
    return (index + 0.5) * 0.4 + PC_RANGE[axis]


def index_of(metres, axis):
    return int(np.floor((metres - PC_RANGE[axis]) / 0.4))


def forward_camera(yaw=0.0):
    """ego2img of a level camera at (0, 0, CAMERA_HEIGHT) looking along +x rotated by yaw
    (nuScenes' front intrinsics on the network input)."""
    K = adjust_intrinsics(np.array([[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]]),
                          (900, 1600), INPUT_HW)
    # camera axes in the ego frame: x right (-y), y down (-z), z forward (+x)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[s, 0, c], [-c, 0, s], [0, -1, 0]])
    T[:3, 3] = (0, 0, CAMERA_HEIGHT)
    K4 = np.eye(4)
    K4[:3, :3] = K
    return K4 @ invert_transform(T)


def geometry(ego2img, bounds=None):
    ego2img = np.asarray(ego2img, np.float64).reshape(-1, 4, 4)
    if bounds is None:
        bounds = image_bounds([(900, 1600)] * len(ego2img), INPUT_HW)
    return (torch.tensor(ego2img, dtype=torch.float32),
            torch.tensor(np.linalg.inv(ego2img), dtype=torch.float32),
            torch.tensor(np.asarray(bounds), dtype=torch.float32))


def observe(labels, ego2img, bounds=None, hazard=None, min_clear=0.0, stray=None):
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE, min_clear)
    if hazard is not None:
        hazard = torch.as_tensor(np.asarray(hazard, np.float32).reshape(-1))
    if stray is not None:
        stray = torch.as_tensor(np.asarray(stray, bool).reshape(-1))
    with torch.inference_mode():
        observed = visibility(torch.from_numpy(np.ascontiguousarray(labels).reshape(-1)),
                              *geometry(ego2img, bounds), hazard=hazard, stray=stray)
    return observed.numpy().reshape(SHAPE).astype(bool)


def in_view(ego2img, bounds):
    """bool [X, Y, Z]: voxel centres in front of the camera and inside its image."""
    grid = np.stack(np.meshgrid(*[centre(np.arange(n), a) for a, n in enumerate(SHAPE)],
                                indexing="ij"), -1)
    p = grid @ ego2img[:3, :3].T + ego2img[:3, 3]
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = p[..., 0] / z, p[..., 1] / z
    u0, v0, u1, v1 = bounds
    return (z > 0.1) & (u >= u0) & (u < u1) & (v >= v0) & (v < v1)


def ground():
    labels = np.full(SHAPE, FREE, np.uint8)
    labels[:, :, index_of(0.0, 2)] = 11                       # driveable surface at z = 0
    return labels


def test_the_road_is_seen_to_the_grid_edge_and_what_lies_under_it_is_not():
    """A ray grazing the road would meet the road's voxel layer metres before each far road
    voxel: the tangent-plane test keeps the far road observed; under it nothing is."""
    ego2img = forward_camera()
    bounds = image_bounds([(900, 1600)], INPUT_HW)[0]
    observed = observe(ground(), ego2img)
    view = in_view(ego2img, bounds)
    road = index_of(0.0, 2)
    far = np.zeros(SHAPE, bool)
    far[index_of(20.0, 0):, :, road] = True                  # 20 m to the grid's edge
    assert (view & far).sum() > 3000
    assert observed[view & far].mean() > 0.99
    assert not observed[:, :, :road].any()                    # under the road
    air = np.zeros(SHAPE, bool)
    air[:, :, road + 1:] = True
    assert observed[view & air].mean() > 0.99                 # nothing else in the way
    assert not observed[~view].any()                          # behind the camera, out of frame


def test_a_wall_hides_what_lies_behind_it():
    labels = ground()
    wall_x = index_of(10.0, 0)
    y0, y1 = index_of(-3.0, 1), index_of(3.0, 1)
    labels[wall_x, y0:y1, index_of(0.0, 2) + 1:] = 15        # 6 m wide, to the grid's top
    ego2img = forward_camera()
    observed = observe(labels, ego2img)
    view = in_view(ego2img, image_bounds([(900, 1600)], INPUT_HW)[0])
    shadow = np.zeros(SHAPE, bool)                            # well inside its shadow
    shadow[wall_x + 2:index_of(30.0, 0), index_of(-1.0, 1):index_of(1.0, 1), 4:10] = True
    assert shadow.sum() > 500 and not observed[shadow].any()
    assert observed[wall_x, y0 + 2:y1 - 2, 4:15].all()        # its face is seen
    front = np.zeros(SHAPE, bool)
    front[index_of(3.0, 0):wall_x - 1, :, index_of(0.0, 2) + 1:] = True
    assert observed[front & view].mean() > 0.99
    aside = np.zeros(SHAPE, bool)       # beside the wall's shadow (its edge: y = 0.3 x)
    aside[index_of(12.0, 0):index_of(15.0, 0), index_of(5.0, 1):index_of(7.0, 1), 4:8] = True
    assert observed[aside & view].mean() > 0.95


def test_stray_voxels_hide_what_lies_behind_them_as_a_wall_of_the_grid_would():
    """A wall the grid calls free but whose voxels hold stray points occludes exactly as
    the same wall labelled occupied; without the stray mask its shadow is seen."""
    labels, walled = ground(), ground()
    wall = np.zeros(SHAPE, bool)
    wall[index_of(10.0, 0), index_of(-3.0, 1):index_of(3.0, 1), index_of(0.0, 2) + 1:] = True
    walled[wall] = 15
    ego2img = forward_camera()
    stray = observe(labels, ego2img, stray=wall)
    np.testing.assert_array_equal(stray, observe(walled, ego2img))
    shadow = np.zeros(SHAPE, bool)
    shadow[index_of(10.0, 0) + 2:index_of(30.0, 0), index_of(-1.0, 1):index_of(1.0, 1), 4:10] = True
    assert not stray[shadow].any() and observe(labels, ego2img)[shadow].all()
    np.testing.assert_array_equal(observe(labels, ego2img, stray=np.zeros(SHAPE, bool)),
                                  observe(labels, ego2img))


def test_a_pole_hides_a_thin_wedge_only():
    labels = ground()
    px, py = index_of(6.0, 0), index_of(0.0, 1)
    labels[px, py, index_of(0.0, 2) + 1:] = 9                # one column of voxels
    ego2img = forward_camera()
    observed = observe(labels, ego2img)
    behind = observed[px + 3:px + 20, py, 4:8]                # straight behind it
    assert not behind.any()
    hidden = ~observed & in_view(ego2img, image_bounds([(900, 1600)], INPUT_HW)[0])
    hidden[:, :, :index_of(0.0, 2) + 1] = False
    # the wedge behind a 0.4 m column is a few voxels wide even at the grid's edge
    assert 0 < hidden.sum() < 0.02 * hidden.size


def ray_past_a_lone_voxel(miss):
    """A lone voxel (a ball occluder) at camera height 8 m ahead, the camera moved sideways so
    that the ray of the depth map cell nearest the voxel passes ``miss`` voxels from its
    centre (the offset horizontal, across the ray) -> the cell's (row, column), the depth
    map (m, inf: nothing stops the ray), the distance of the voxel's centre along that cell's
    ray (m) and every cell's ray's distance from the centre (voxels)."""
    labels = np.full(SHAPE, FREE, np.uint8)
    ball = np.array([index_of(8.0, 0), index_of(0.0, 1), index_of(CAMERA_HEIGHT, 2)])
    labels[tuple(ball)] = 9
    centre_m = np.array([centre(i, a) for a, i in enumerate(ball)])
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE, 0.0)
    ego2img = forward_camera()

    def cell_rays(ego2img):
        cells = visibility.camera_cells(*geometry(ego2img, image_bounds([(900, 1600)],
                                                                        INPUT_HW))[1:])
        hx, hy, tan = (t[0].double().numpy() for t in visibility.rays(*cells)[:3])
        direction = np.stack(np.broadcast_arrays(hx[None], hy[None], tan[:, None]), -1)
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)     # [E, A, 3]
        return cells, cells[0][0].double().numpy(), direction

    # the cell whose ray comes nearest the voxel's centre, then the camera moved across it
    _, origin, direction = cell_rays(ego2img)
    to_ball = centre_m - origin
    off = to_ball - (direction @ to_ball)[..., None] * direction
    row, column = np.unravel_index(np.linalg.norm(off, axis=-1).argmin(), off.shape[:2])
    d = direction[row, column]
    across = np.cross(d, (0.0, 0.0, 1.0))
    across /= np.linalg.norm(across)
    shift = off[row, column] - miss * 0.4 * across          # the ray then misses by ``miss``
    moved = ego2img.copy()
    moved[:3, 3] -= moved[:3, :3] @ shift                   # the camera at origin + shift
    cells, origin, direction = cell_rays(moved)
    to_ball = centre_m - origin
    along = direction @ to_ball
    misses = np.linalg.norm(to_ball - along[..., None] * direction, axis=-1) / 0.4
    assert misses[row, column] == pytest.approx(miss, abs=1e-3)
    kind = visibility.occluders(torch.from_numpy(labels.reshape(-1)))
    with torch.inference_mode():
        depth = visibility.depth_maps(kind, *cells)[0][0].numpy()
    return (row, column), depth, along[row, column], misses


def test_a_ball_occluder_stops_a_ray_through_its_voxel_but_not_one_beside_it():
    """An edge or corner voxel hides what is behind it up to the radius of its inscribed
    sphere: a ray 0.45 voxel from its centre crosses the voxel and is stopped at the voxel,
    one 0.7 voxel from it (outside the voxel) is not; nor is any other cell's ray farther
    than half a voxel from the centre."""
    (row, column), depth, along, misses = ray_past_a_lone_voxel(0.45)
    assert depth[row, column] == pytest.approx(along, abs=0.1)
    (row, column), depth, _, misses = ray_past_a_lone_voxel(0.7)
    assert np.isinf(depth[row, column])
    stopped, near = np.isfinite(depth), misses < 0.5
    assert stopped.any()                                # the rows near the horizon are dense
    clear_cut = np.abs(misses - 0.5) > 0.02
    np.testing.assert_array_equal(stopped[clear_cut], near[clear_cut])


def test_only_what_the_image_shows_is_observed():
    """The whole camera image counts, the rows the network input crops off its top too."""
    ego2img = forward_camera()
    whole = image_bounds([(900, 1600)], INPUT_HW)
    assert whole[0].tolist() == [0.0, -70.0, 352.0, 128.0]
    cropped = np.array([[0.0, 0.0, 352.0, 128.0]], np.float32)
    # 3 to 4.2 m high at 8 to 10 m: above the cropped input's top row, below the image's
    high_and_near = np.zeros(SHAPE, bool)
    high_and_near[index_of(8.0, 0):index_of(10.0, 0), index_of(-1.0, 1):index_of(1.0, 1),
                  index_of(3.0, 2) + 1:index_of(4.2, 2)] = True
    assert high_and_near.sum() >= 50
    assert observe(ground(), ego2img, whole)[high_and_near].all()
    assert not observe(ground(), ego2img, cropped)[high_and_near].any()


def test_every_camera_of_a_ring_counts():
    rig = np.stack([forward_camera(yaw) for yaw in np.radians([0, -55, 55, 180, 110, -110])])
    bounds = image_bounds([(900, 1600)] * 6, INPUT_HW)
    observed = observe(ground(), rig, bounds)
    ring = np.zeros(SHAPE, bool)
    x, y = np.meshgrid(centre(np.arange(200), 0), centre(np.arange(200), 1), indexing="ij")
    ring[(np.hypot(x, y) > 15) & (np.hypot(x, y) < 35), 6] = True
    assert observed[ring].mean() > 0.95


def test_broken_geometry_observes_nothing_and_raises_nothing():
    ego2img = np.full((1, 4, 4), np.nan)
    observed = observe(ground(), ego2img, image_bounds([(900, 1600)], INPUT_HW))
    assert not observed.any()


def band(rate, x0=10.0, x1=12.0):
    """A hazard of ``rate`` per voxel length over the free voxels above the road with
    x0 <= x < x1 (m), 0 elsewhere."""
    hazard = np.zeros(SHAPE, np.float32)
    hazard[index_of(x0, 0):index_of(x1, 0), :, index_of(0.0, 2) + 1:] = rate
    return hazard


def test_an_uncertain_band_hides_what_lies_beyond_it_when_a_clear_ray_is_too_unlikely():
    """Rays to 1-2.6 m high cross a 2 m (5 voxels) band of rate 0.14 almost level: clear with
    probability ~exp(-0.7) = 0.5. Seen beyond it at min_clear 0.3, hidden at 0.8; in front
    of it and without a hazard, seen either way."""
    ego2img = forward_camera()
    beyond, front = np.zeros(SHAPE, bool), np.zeros(SHAPE, bool)
    rows = slice(index_of(1.0, 2), index_of(2.6, 2))
    beyond[index_of(16.0, 0):index_of(30.0, 0), index_of(-1.0, 1):index_of(1.0, 1), rows] = True
    front[index_of(4.0, 0):index_of(9.0, 0), index_of(-1.0, 1):index_of(1.0, 1), rows] = True
    hazard = band(0.14)
    for min_clear, seen_beyond in ((0.3, True), (0.8, False)):
        observed = observe(ground(), ego2img, hazard=hazard, min_clear=min_clear)
        assert observed[front].all()
        assert observed[beyond].all() == seen_beyond and observed[beyond].any() == seen_beyond
    hard = observe(ground(), ego2img)
    assert hard[beyond].all()
    np.testing.assert_array_equal(observe(ground(), ego2img, hazard=band(0.0), min_clear=0.8),
                                  hard)
    np.testing.assert_array_equal(observe(ground(), ego2img, hazard=hazard, min_clear=0.0),
                                  hard)
    # the road beyond the band: its rays pass lower, through the band too
    road = np.zeros(SHAPE, bool)
    road[index_of(20.0, 0):index_of(30.0, 0), index_of(-1.0, 1):index_of(1.0, 1),
         index_of(0.0, 2)] = True
    assert hard[road].all()
    assert not observe(ground(), ego2img, hazard=band(0.3), min_clear=0.8)[road].any()


def test_the_step_hides_exactly_where_the_fitted_optical_depth_passes_the_limit():
    """The hazard is fitted on Visibility.optical_paths (train/calibrate.py); the step hides a
    voxel the predicted surfaces leave seen exactly when that optical depth passes
    -log(min_clear) (up to float ties)."""
    from testing.helpers import driving_scene
    rng = np.random.default_rng(1)
    labels = driving_scene(rng)
    hazard = (rng.random(SHAPE) ** 4 * 0.02).astype(np.float32)
    hazard[labels != FREE] = 0
    rig = np.stack([forward_camera(yaw) for yaw in np.radians([0, -55, 55, 180, 110, -110])])
    bounds = image_bounds([(900, 1600)] * 6, INPUT_HW)
    min_clear = 0.7
    hard = observe(labels, rig, bounds)
    soft = observe(labels, rig, bounds, hazard=hazard, min_clear=min_clear)
    assert not (soft & ~hard).any()
    voxels = np.flatnonzero(hard)
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE, min_clear)
    with torch.inference_mode():
        depth = visibility.optical_paths(torch.from_numpy(hazard)[None], *geometry(rig, bounds),
                                         torch.from_numpy(voxels))[:, 0].numpy()
    limit = -np.log(min_clear)
    clear = depth <= limit
    assert 0.1 < clear.mean() < 0.9                              # a real comparison
    ties = np.abs(depth - limit) < 1e-4
    assert (soft.ravel()[voxels] == clear)[~ties].all()


def test_optical_paths_add_up_per_hazard():
    """K hazards at once give the sum of each alone: the fit's features are linear."""
    from testing.helpers import driving_scene
    rng = np.random.default_rng(2)
    labels = driving_scene(rng)
    rates = torch.from_numpy((rng.random((3, *SHAPE)) * 0.1).astype(np.float32))
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE, 0.5)
    geo = geometry(forward_camera())
    with torch.inference_mode():
        voxels = torch.from_numpy(np.flatnonzero(visibility(
            torch.from_numpy(labels.reshape(-1)), *geo).numpy()))
        each = visibility.optical_paths(rates, *geo, voxels, chunk=2)
        summed = visibility.optical_paths(rates.sum(0, keepdim=True), *geo, voxels)
    torch.testing.assert_close(each.sum(-1), summed[:, 0], rtol=1e-4, atol=1e-4)
    assert (each > 0).all(-1).float().mean() > 0.5


def busy_scene(seed):
    """Labels and a hazard of a street: the road, cars, poles, walls, loose voxels."""
    rng = np.random.default_rng(seed)
    labels = np.full(SHAPE, FREE, np.uint8)
    labels[:, :, index_of(0.0, 2)] = 11
    for _ in range(40):
        x, y = rng.integers(0, 190, 2)
        labels[x:x + rng.integers(4, 12), y:y + rng.integers(4, 6), 3:3 + rng.integers(3, 6)] = 1
    for _ in range(20):
        x, y = rng.integers(0, 200, 2)
        labels[x, y, 3:14] = 2
    for _ in range(2):
        labels[rng.integers(0, 200), 20:180, 3:12] = 3
    labels[rng.random(SHAPE) < 0.002] = 5
    hazard = (rng.random(SHAPE) * 0.004).astype(np.float32) * (labels == FREE)
    return labels, hazard


# (observed voxels, sha256 of the packed mask) of busy_scene(seed) seen by a ring of six
# cameras at min_clear 0.85: the same on AVX2 and AVX-512 kernels
BUSY_SCENES = {0: (120846, "83827a7970549cbb"), 1: (125614, "2f717c0f34d5fbb9")}


@pytest.mark.parametrize("seed", sorted(BUSY_SCENES))
def test_a_busy_scene_is_observed_bit_for_bit_as_before(seed):
    """Speed work must not move a single voxel: where the visibility is meant to change,
    compare it with the revision before on the node's own grids (python -m
    tools.visibility_identity) and update BUSY_SCENES."""
    import hashlib
    labels, hazard = busy_scene(seed)
    rig = np.stack([forward_camera(yaw) for yaw in np.radians([0, -55, 55, 180, 110, -110])])
    observed = observe(labels, rig, image_bounds([(900, 1600)] * 6, INPUT_HW), hazard,
                       min_clear=0.85)
    digest = hashlib.sha256(np.packbits(observed.reshape(-1))).hexdigest()[:16]
    assert (int(observed.sum()), digest) == BUSY_SCENES[seed]


def test_min_clear_is_a_probability():
    for bad in (-0.1, 1.0, 2.0):
        with pytest.raises(ValueError, match="min_clear"):
            Visibility(SHAPE, PC_RANGE, 0.4, FREE, bad)


def test_no_host_read_inside_it():
    from odg_ros.bench.census import Census, CensusMode
    ego2img = forward_camera()[None]
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE, 0.8)
    args = (torch.from_numpy(ground().reshape(-1)), torch.tensor(ego2img, dtype=torch.float32),
            torch.tensor(np.linalg.inv(ego2img), dtype=torch.float32),
            torch.tensor(image_bounds([(900, 1600)], INPUT_HW)))
    for hazard in (None, torch.from_numpy(band(0.1).reshape(-1))):
        census = Census()
        # (no_grad, not inference_mode: an inference tensor's .item() bypasses the mode)
        with torch.no_grad(), CensusMode(census, device_type=None):
            visibility(*args, hazard=hazard)
        assert census.per_step(census.ops) > 100
        assert census.per_step(census.syncs) == 0, census.report()


@pytest.mark.timeout(300)
def test_agreement_with_a_synthetic_worlds_mask_camera(tmp_path):
    """One keyframe of a generated world: the observed voxels of its ground-truth grid
    against its mask_camera (the benchmark over the val split: tools/visibility_agreement.py,
    0.85 there)."""
    import os
    from odg_ros.data.occ_io import load_occ
    from odg_ros.data.synth import generate as G, sensor_rig
    from odg_ros.data.synth.tables import token
    G.generate(str(tmp_path), scenes=1, seconds=0.5, seed=3, image_hw=(54, 96),
               progress=False)
    world = G.scene_world(3, 0, 0.5)
    semantics, _, mask = load_occ(os.path.join(tmp_path, "gts", G.scene_name(0),
                                               token(3, "sample", 0, 0), "labels.npz"))
    T_ego_global = invert_transform(world.ego_pose(G.keyframe_time(0)))
    ego2img = []
    for cam in sensor_rig.cameras((54, 96)):
        T = T_ego_global @ world.ego_pose(G.camera_time(0, cam.name)) @ cam.T_ego_from_cam
        K4 = np.eye(4)
        K4[:3, :3] = adjust_intrinsics(cam.intrinsics, (54, 96), INPUT_HW)
        ego2img.append(K4 @ invert_transform(T))
    observed = observe(semantics, np.stack(ego2img), image_bounds([(54, 96)] * 6, INPUT_HW))
    iou = (observed & mask).sum() / (observed | mask).sum()
    print(f"IoU of observed against mask_camera: {iou:.3f}")
    assert iou > 0.75           # 0.760 measured on this keyframe (0.78 with 0.35-voxel balls)


def test_the_predictor_without_visibility_returns_none():
    from testing.online import make_model, make_sets
    from odg_ros.online.predictor import OnlinePredictor
    model, cfg = make_model()
    images, ego2img, pose, stamp = make_sets(cfg, 1)[0]
    on = OnlinePredictor(model, cfg, "cpu").step(images, ego2img, pose, stamp)
    off = OnlinePredictor(model, cfg, "cpu", visibility=False).step(images, ego2img, pose,
                                                                   stamp)
    assert on.observed.shape == on.grid.shape and on.observed.any()
    assert off.observed is None
    np.testing.assert_array_equal(on.grid, off.grid)


def tilted_camera(yaw, pitch, roll, height):
    """ego2img of forward_camera's camera turned by pitch (about the ego y axis: positive
    looks down) and roll (about its optical axis), at ``height`` (m)."""
    K = adjust_intrinsics(np.array([[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]]),
                          (900, 1600), INPUT_HW)
    c, s = np.cos(yaw), np.sin(yaw)
    looking = np.array([[s, 0, c], [-c, 0, s], [0, -1, 0]])
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    turn = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    twist = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])        # about the camera's z
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ turn \
        @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ looking @ twist
    T[:3, 3] = (0, 0, height)
    K4 = np.eye(4)
    K4[:3, :3] = K
    return K4 @ invert_transform(T)


@pytest.mark.parametrize("yaw, pitch, roll, height", [
    (0.0, 0.0, 0.0, 1.6), (0.4, 0.35, 0.0, 2.0), (-1.2, -0.3, 0.25, 0.5),
    (2.5, 0.8, -0.6, 3.0), (3.1, 0.7, 1.2, 6.0)])
def test_the_image_test_is_the_projection_of_each_voxel_centre(yaw, pitch, roll, height):
    """in_image (a range of layers per column) against projecting every voxel centre in
    float64, cameras looking up, down and rolled so that the image cuts columns at both
    ends: the same wherever a centre is not within a thousandth of a pixel of an edge."""
    ego2img = tilted_camera(yaw, pitch, roll, height)
    bounds = image_bounds([(900, 1600)], INPUT_HW)
    visibility = Visibility(SHAPE, PC_RANGE, 0.4, FREE)
    e, _, b = geometry(ego2img, bounds)
    camera = torch.zeros(SHAPE[:2], dtype=torch.long)
    got = visibility.in_image(e, b, camera).numpy()
    want = in_view(ego2img, bounds[0])
    grid = np.stack(np.meshgrid(*[centre(np.arange(n), a) for a, n in enumerate(SHAPE)],
                                indexing="ij"), -1)
    p = grid @ ego2img[:3, :3].T + ego2img[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    u0, v0, u1, v1 = bounds[0]
    edge = np.min(np.abs(np.stack([u - u0, u - u1, v - v0, v - v1])), 0) < 1e-3
    clear = ~edge & (np.abs(p[..., 2]) > 0.2)
    np.testing.assert_array_equal(got[clear], want[clear])
    # some columns hold the image over part of their height only
    partial = got.any(-1) & ~got.all(-1)
    assert partial.sum() > 100 and want.sum() > 1000
