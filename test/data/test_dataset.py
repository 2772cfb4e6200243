"""OccDataset, LiDAR render targets and history selection on a tiny hand-built dataroot.

The world: one scene, keyframes every 6th 12 Hz camera set (0.5 s), the ego drives along +x at
SPEED m/s; camera n of a set is stamped 7 + 8 n ms after the set (LiDAR) time, with its own ego
pose, as in nuScenes. Every camera image is a solid colour that encodes (set, camera).
"""
import copy

import numpy as np
import pytest
import torch
from PIL import Image

from odg_ros import geometry, preprocess
from odg_ros.classes import FREE_LABEL
from odg_ros.model_config import ModelConfig
from odg_ros.data import lidar
from odg_ros.data.batch import collate
from odg_ros.nuscenes_cameras import CAMERA_NAMES
from odg_ros.data.dataset import OccDataset, select_history
from testing.tiny_world import CAM_OFFSET_US, CAM_T, CX, CY, FOCAL, IMAGE_HW, NEAR, ORIGIN, R_ego_from_front_cam, Rz, SET_PERIOD_US, SPEED, build_world, colour, lidar_points_ego

INPUT_HW = (32, 64)            # scale 0.4 -> resized 36 x 64, crop 4 rows off the top


def cfg(num_frames=3):
    return ModelConfig(image_size=INPUT_HW, num_frames=num_frames)


@pytest.fixture()
def world(tmp_path):
    return build_world(tmp_path)


def hand_pixel(point_ego_cam_stamp):
    """Front camera: ego point at the camera's stamp -> network-input (u, v, depth) by hand."""
    x, y, z = np.asarray(point_ego_cam_stamp) - CAM_T
    depth = x                                   # forward
    u = FOCAL * (-y) / depth + CX               # right = -left
    v = FOCAL * (-z) / depth + CY               # down = -up
    scale, crop_top = 64 / 160, 4
    return u * scale, v * scale - crop_top, depth


# --------------------------------------------------------------------------- contract
def test_gt_boxes_outside_the_grid_are_dropped(world):
    """The infos keep objects out to the annotation range; the grid (and every query) ends
    at +-40 m, so only boxes whose centre is inside [x_min, x_max) x [y_min, y_max) stay."""
    infos = copy.deepcopy(world)
    boxes = np.tile(infos["infos"][2]["gt_boxes"], (5, 1))
    boxes[:, :2] = [[10.0, 2.0], [45.0, 0.0], [39.9, -40.0], [0.0, 40.0], [-40.5, 3.0]]
    infos["infos"][2].update(gt_boxes=boxes, gt_labels=np.array([0, 1, 5, 8, 9]))
    s = OccDataset(infos, cfg())[2]
    np.testing.assert_allclose(s["gt_boxes"][:, :2].numpy(), [[10.0, 2.0], [39.9, -40.0]])
    assert s["gt_labels"].tolist() == [0, 5]
    np.testing.assert_array_equal(geometry.inside_bev_range(boxes, cfg().pc_range),
                                  [True, False, True, False, False])


def test_shapes_and_dtypes(world):
    ds = OccDataset(world, cfg())
    assert len(ds) == 3
    s = ds[2]
    T, N, (H, W) = 3, 6, INPUT_HW
    expect = {"images": ((T, N, H, W, 3), torch.uint8), "ego2img": ((T, N, 4, 4), torch.float32),
              "ego_warp": ((T, 4, 4), torch.float32), "time_delta": ((T,), torch.float32),
              "intrinsics": ((N, 3, 3), torch.float32), "cam_from_ego": ((N, 4, 4), torch.float32),
              "occ_semantics": ((200, 200, 16), torch.uint8),
              "occ_mask_camera": ((200, 200, 16), torch.bool),
              "occ_mask_lidar": ((200, 200, 16), torch.bool),
              "gt_boxes": ((1, 9), torch.float32), "gt_labels": ((1,), torch.int64)}
    for key, (shape, dtype) in expect.items():
        assert tuple(s[key].shape) == shape and s[key].dtype == dtype, key
    assert isinstance(s["render_targets"], list) and len(s["render_targets"]) == N
    assert all(t.dtype == torch.float32 and t.shape[1] == 4 for t in s["render_targets"])
    assert s["token"] == "kf2" and s["has_occ"] is True
    assert s["occ_semantics"][130, 102, 6] == 4 and s["occ_mask_camera"][125, 95, 3]
    # ego2img[0] = [K 0; 0 1] @ cam_from_ego, and intrinsics are the input's
    P = torch.eye(4).repeat(N, 1, 1)
    P[:, :3, :3] = s["intrinsics"]
    torch.testing.assert_close(s["ego2img"][0], P @ s["cam_from_ego"], rtol=1e-5, atol=1e-3)
    K = preprocess.adjust_intrinsics([[FOCAL, 0, CX], [0, FOCAL, CY], [0, 0, 1]], IMAGE_HW, INPUT_HW)
    torch.testing.assert_close(s["intrinsics"][0].double(), torch.from_numpy(K), rtol=0, atol=1e-5)
    torch.testing.assert_close(s["ego_warp"][0], torch.eye(4))
    assert s["time_delta"][0] == 0


def test_images_are_the_chosen_sets(world):
    s = OccDataset(world, cfg())[2]
    # keyframe 2 = set 12; eval interval 6 -> sets 6 and 0 (the previous keyframes)
    assert s["images"].dtype == torch.uint8      # normalised on the device (batch.to_device)
    for t, set_index in enumerate((12, 6, 0)):
        for n in range(6):
            got = s["images"][t, n].float().mean(dim=(0, 1))
            torch.testing.assert_close(got, torch.tensor(colour(set_index, n), dtype=torch.float32),
                                       rtol=0, atol=3.0)


# --------------------------------------------------------------------------- geometry
def test_ego2img_hand_computed_pixel(world):
    s = OccDataset(world, cfg())[2]
    # the front camera's stamp is 7 ms after the keyframe: its ego is 0.07 m further along x
    shift = SPEED * CAM_OFFSET_US[0] * 1e-6
    u, v, d = hand_pixel(NEAR - [shift, 0, 0])
    p = s["ego2img"][0, 0].double() @ torch.tensor([*NEAR, 1.0], dtype=torch.float64)
    assert abs(p[2].item() - d) < 1e-3
    assert abs(p[0].item() / p[2].item() - u) < 2e-3 and abs(p[1].item() / p[2].item() - v) < 2e-3
    # ignoring the 7 ms of ego motion would move the pixel measurably
    u_static, _, _ = hand_pixel(NEAR)
    assert abs(u_static - u) > 0.02


def test_every_camera_sees_its_own_stamp(world):
    """A static global point projects to the same pixel whether we go through frame t's
    reference ego or directly through each camera's own pose."""
    ds = OccDataset(world, cfg())
    s = ds[2]
    info = world["infos"][2]
    g = np.array([*(ORIGIN + [22.0, -3.0, 1.0]), 1.0])             # global point
    sets = [info["cams"], world["infos"][1]["cams"], world["infos"][0]["cams"]]
    refs = [info["ego_pose"], sets[1]["CAM_FRONT"]["ego_pose"], sets[2]["CAM_FRONT"]["ego_pose"]]
    K = preprocess.adjust_intrinsics([[FOCAL, 0, CX], [0, FOCAL, CY], [0, 0, 1]], IMAGE_HW, INPUT_HW)
    for t in range(3):
        p_ref = geometry.invert_transform(refs[t]) @ g
        # warp consistency: ego_warp[t] @ (point in frame 0 ego) = point in frame t ego
        p0 = geometry.invert_transform(info["ego_pose"]) @ g
        np.testing.assert_allclose(s["ego_warp"][t].double().numpy() @ p0, p_ref, atol=1e-3)
        for n, name in enumerate(CAMERA_NAMES):
            cam = sets[t][name]
            p_cam = (geometry.invert_transform(cam["sensor2ego"])
                     @ geometry.invert_transform(cam["ego_pose"]) @ g)
            direct = K @ p_cam[:3]
            got = s["ego2img"][t, n].double().numpy() @ p_ref
            np.testing.assert_allclose(got[:3], direct, rtol=1e-5, atol=2e-3)


def test_ego_warp_known_pose_pair(tmp_path):
    world = build_world(tmp_path, yaw_rate=0.4, with_lidar=False)
    s = OccDataset(world, cfg())[2]
    # frame 0: keyframe 2 at tau0 = 12 sets; frame 1: set 6's CAM_FRONT at tau1
    tau0 = 12 * SET_PERIOD_US * 1e-6
    tau1 = (6 * SET_PERIOD_US + CAM_OFFSET_US[0]) * 1e-6
    yaw0, yaw1 = 0.4 * tau0, 0.4 * tau1
    # by hand: T_1_from_0 = inv(P1) P0 with P = [Rz(yaw) | origin + (v tau, 0, 0)]
    dyaw = yaw0 - yaw1
    dx_global = SPEED * (tau0 - tau1)
    c, sn = np.cos(yaw1), np.sin(yaw1)
    trans = np.array([c * dx_global, -sn * dx_global, 0.0])       # Rz(-yaw1) @ (dx, 0, 0)
    expected = np.eye(4)
    expected[:3, :3] = [[np.cos(dyaw), -np.sin(dyaw), 0], [np.sin(dyaw), np.cos(dyaw), 0], [0, 0, 1]]
    expected[:3, 3] = trans
    np.testing.assert_allclose(s["ego_warp"][1].double().numpy(), expected, atol=2e-5)
    assert abs(s["time_delta"][1].item() - (tau0 - tau1)) < 1e-6
    assert abs(s["time_delta"][2].item() - (tau0 - CAM_OFFSET_US[0] * 1e-6)) < 1e-6


def test_time_delta(world):
    s = OccDataset(world, cfg())[2]
    expected = [0.0, 6 * SET_PERIOD_US * 1e-6 - 0.007, 12 * SET_PERIOD_US * 1e-6 - 0.007]
    torch.testing.assert_close(s["time_delta"], torch.tensor(expected), rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- history choice
def test_history_selection_rules():
    assert select_history(0, 3) == [-1, -1, -1]
    assert select_history(42, 7) == [5, 11, 17, 23, 29, 35, 41]
    assert select_history(20, 7) == [5, 11, 17, 19, 19, 19, 19]     # oldest repeated
    assert select_history(5, 7, train=True) == [0, 1, 2, 3, 4, 4, 4]
    assert select_history(10, 7, train=True) == [0, 1, 2, 3, 4, 5, 6]  # interval capped at 1
    seen = set()
    g = torch.Generator().manual_seed(0)
    for _ in range(200):
        idx = select_history(60, 7, train=True, generator=g)
        interval = idx[0] + 1
        assert 4 <= interval <= 8 and idx == [(k + 1) * interval - 1 for k in range(7)]
        seen.add(interval)
    assert seen == {4, 5, 6, 7, 8}


def test_history_repeats_oldest_and_self(world):
    ds = OccDataset(world, cfg())
    s1 = ds[1]          # 6 earlier sets (5 sweeps + keyframe 0): indices 5 and 11 -> set 0 twice
    torch.testing.assert_close(s1["time_delta"][1], s1["time_delta"][2])
    torch.testing.assert_close(s1["ego2img"][1], s1["ego2img"][2])
    s0 = ds[0]          # first keyframe: no earlier set -> repeats itself
    for t in (1, 2):
        torch.testing.assert_close(s0["ego_warp"][t], torch.eye(4))
        assert s0["time_delta"][t] == 0
        torch.testing.assert_close(s0["images"][t], s0["images"][0])
        torch.testing.assert_close(s0["ego2img"][t], s0["ego2img"][0])


def test_sweeps_spanning_keyframes_give_the_same_sample(tmp_path):
    """Infos whose sweeps already run through the previous keyframes load identically."""
    a = OccDataset(build_world(tmp_path / "a"), cfg())[2]
    b = OccDataset(build_world(tmp_path / "b", sweeps_span_all=True), cfg())[2]
    for key in ("ego2img", "ego_warp", "time_delta", "images"):
        torch.testing.assert_close(a[key], b[key])


def test_train_mode_picks_valid_sets(world):
    ds = OccDataset(world, cfg(num_frames=3), train=True)
    torch.manual_seed(3)
    s = ds[2]          # 12 earlier sets, 2 history frames: interval in 4..6
    dt1 = s["time_delta"][1].item()
    steps = round((dt1 + 0.007) / (SET_PERIOD_US * 1e-6))
    assert 4 <= steps <= 6
    assert abs(s["time_delta"][2].item() + 0.007 - 2 * steps * SET_PERIOD_US * 1e-6) < 1e-5


# --------------------------------------------------------------------------- LiDAR targets
def test_render_targets_hand_computed(world):
    from odg_ros.data.lidarseg import lidarseg_to_occ
    s = OccDataset(world, cfg())[2]
    targets = s["render_targets"]
    _, raw = lidar_points_ego()
    occ = lidarseg_to_occ(raw)
    shift = SPEED * CAM_OFFSET_US[0] * 1e-6
    u, v, d = hand_pixel(NEAR - [shift, 0, 0])
    front = targets[0].numpy()
    assert len(front) == 1, front                         # FAR hidden, CLOSE dropped, OUT outside
    np.testing.assert_allclose(front[0, :3], [u, v, d], atol=2e-3)
    assert front[0, 3] == occ[0]
    back = targets[3].numpy()                             # BACK: seen by CAM_BACK
    shift_back = SPEED * (CAM_OFFSET_US[0] + 3 * CAM_OFFSET_US[1]) * 1e-6
    depth_back = CAM_T[0] - (-10.0 - shift_back)
    assert len(back) == 1
    np.testing.assert_allclose(back[0, :3], [CX * 0.4, CY * 0.4 - 4, depth_back], atol=2e-3)
    assert back[0, 3] == occ[2]
    for n in (1, 2, 4, 5):
        assert len(targets[n]) == 0


def test_missing_lidarseg_gives_empty_targets(world):
    world["infos"][2]["lidarseg_path"] = ""
    s = OccDataset(world, cfg())[2]
    assert all(t.shape == (0, 4) for t in s["render_targets"])


def test_project_matches_bruteforce_reference():
    """lidar_render_targets vs a per-point float64 loop on random points and cameras."""
    rng = np.random.default_rng(0)
    pts = rng.uniform([-30, -30, -2], [30, 30, 4], (3000, 3))
    labels = rng.integers(0, 19, 3000).astype(np.uint8)   # 17, 18 are not classes
    hw = (48, 96)
    ego2img = []
    for n in range(3):
        K = np.array([[60.0, 0, 48], [0, 60.0, 30], [0, 0, 1]])
        T = geometry.make_transform(Rz(rng.uniform(-180, 180)) @ R_ego_from_front_cam(),
                                    rng.normal(0, 1, 3))
        ego2img.append(geometry.ego_to_image(K, T))
    ego2img = np.stack(ego2img)
    valid = [48, 40, 48]
    got = lidar.lidar_render_targets(pts, labels, ego2img, hw, valid, num_classes=17)
    for n in range(3):
        best = {}
        for p, lab in zip(pts, labels):
            if lab >= 17:
                continue
            x, y, z, _ = ego2img[n] @ [*p, 1.0]
            if z < lidar.MIN_DEPTH:
                continue
            u, v = x / z, y / z
            if 0 <= u < hw[1] and 0 <= v < valid[n]:
                key = (int(np.floor(v)), int(np.floor(u)))
                if key not in best or z < best[key][2]:
                    best[key] = (u, v, z, lab)
        ref = np.array(sorted(best.values())) if best else np.zeros((0, 4))
        mine = got[n][np.lexsort(got[n][:, ::-1].T)] if len(got[n]) else got[n]
        assert len(ref) > 20 and mine.shape == ref.shape
        np.testing.assert_allclose(mine, ref, rtol=1e-5, atol=1e-3)


def test_lidar_file_errors(tmp_path):
    path = tmp_path / "bad.pcd.bin"
    np.zeros(7, np.float32).tofile(path)
    with pytest.raises(ValueError, match="multiple of 5"):
        lidar.load_points(path)
    np.zeros(10, np.float32).tofile(path)
    assert lidar.load_points(path).shape == (2, 5)
    seg = tmp_path / "seg.bin"
    np.zeros(3, np.uint8).tofile(seg)
    with pytest.raises(ValueError, match="3 labels for 2 points"):
        lidar.load_lidarseg(seg, 2)
    with pytest.raises(FileNotFoundError):
        lidar.load_points(tmp_path / "none.bin")


# --------------------------------------------------------------------------- GT and errors
def test_missing_gt(tmp_path):
    world = build_world(tmp_path, occ=False, with_lidar=False)
    s = OccDataset(world, cfg())[1]
    assert s["has_occ"] is False
    assert (s["occ_semantics"] == FREE_LABEL).all()
    assert not s["occ_mask_camera"].any() and not s["occ_mask_lidar"].any()
    # a path that does not resolve is a configuration error, not "no GT"
    world["infos"][1]["occ_path"] = "scene-0001/kf1/labels.npz"
    with pytest.raises(FileNotFoundError, match="occ_root"):
        OccDataset(world, cfg())[1]


def test_bad_inputs_raise(world, tmp_path):
    with pytest.raises(ValueError, match="num_cams"):
        OccDataset(world, cfg().replace(num_cams=5))
    world["infos"][2]["cams"]["CAM_BACK"]["ego_pose"] = np.full((4, 4), np.nan)
    with pytest.raises(ValueError, match="rigid"):
        OccDataset(world, cfg())[2]
    wrong = build_world(tmp_path / "w", with_lidar=False)
    wrong["infos"][0]["cams"]["CAM_FRONT"]["image_hw"] = (900, 1600)
    with pytest.raises(ValueError, match="infos say"):
        OccDataset(wrong, cfg())[0]


def test_dataloader_workers(world, tmp_path):
    import pickle
    path = tmp_path / "infos.pkl"
    with open(path, "wb") as f:
        pickle.dump(world, f)
    ds = OccDataset(path, cfg())
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2, collate_fn=collate)
    batches = list(loader)
    assert [len(b["token"]) for b in batches] == [2, 1]
    b = batches[0]
    assert b["images"].shape == (2, 3, 6, *INPUT_HW, 3) and b["ego2img"].shape == (2, 3, 6, 4, 4)
    assert isinstance(b["render_targets"], list) and len(b["render_targets"]) == 2
    torch.testing.assert_close(b["ego2img"][1], ds[1]["ego2img"])


def test_jpeg_draft_decode_keeps_geometry(tmp_path):
    """Reduced-scale JPEG decoding lands edges where the full-decode path puts them."""
    from odg_ros.data.decode import decode_resized
    img = np.full((360, 640, 3), 40, np.uint8)
    img[:, 201:205] = 250           # vertical line, centre x = 203 (corner convention)
    img[250:254, :] = 250           # horizontal line, centre y = 252
    Image.fromarray(img).save(tmp_path / "lines.jpg", quality=95)
    dst = (64, 176)                 # scale 0.275: resized 99 x 176, crop 35 rows
    with Image.open(tmp_path / "lines.jpg") as im:
        fast = decode_resized(im, dst).astype(float)[..., 0] - 40
        assert im.size == (320, 180)                     # decoded at 1/2 scale
    with Image.open(tmp_path / "lines.jpg") as im:
        full = preprocess.resize_crop(np.asarray(im.convert("RGB")), dst).astype(float)[..., 0] - 40

    def centroid(profile):
        return (np.arange(len(profile)) * profile).sum() / profile.sum()

    for out in (fast, full):
        x = centroid(out[:25, 45:68].mean(0)) + 45      # rows clear of the horizontal line
        y = centroid(out[20:50, 100:].mean(1)) + 20     # columns clear of the vertical line
        assert abs(x - (203 * 0.275 - 0.5)) < 0.1
        assert abs(y - (252 * 0.275 - 35 - 0.5)) < 0.1
    assert np.abs(fast - full).mean() < 3


def test_occ_root_resolution(tmp_path):
    world = build_world(tmp_path, with_lidar=False)
    (tmp_path / "gts").rename(tmp_path / "occ3d")
    with pytest.raises(FileNotFoundError):
        OccDataset(world, cfg())[0]
    assert OccDataset(world, cfg(), occ_root=tmp_path / "occ3d")[0]["has_occ"]
    world["occ_root"] = "occ3d"                     # relative to dataroot, as odg score reads it
    assert OccDataset(world, cfg())[0]["has_occ"]


def test_waymo_layout(tmp_path):
    """A Waymo-style infos: 5 cameras in their stored order, Occ3D-Waymo GT (free 15)."""
    world = build_world(tmp_path, with_lidar=False, occ=False)
    names = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
    source = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
    for info in world["infos"]:
        info["cams"] = {w: info["cams"][c] for w, c in zip(names, source)}
        info["sweeps"] = [{w: s[c] for w, c in zip(names, source)} for s in info["sweeps"]]
    world["dataset"] = "waymo"
    label = np.full((200, 200, 16), 23, np.uint8)
    label[100, 100, 3] = 13                        # road
    state = np.ones((200, 200, 16), np.uint8)
    (tmp_path / "gts" / "000").mkdir(parents=True)
    np.savez_compressed(tmp_path / "gts" / "000" / "002_04.npz", voxel_label=label,
                        origin_voxel_state=state, final_voxel_state=state, infov=state)
    world["infos"][2]["occ_path"] = "000/002_04.npz"
    waymo_cfg = cfg().replace(num_cams=5, dataset="waymo", num_classes=15)
    s = OccDataset(world, waymo_cfg)[2]
    assert s["images"].shape == (3, 5, *INPUT_HW, 3) and s["ego2img"].shape == (3, 5, 4, 4)
    assert s["has_occ"] and s["occ_semantics"][100, 100, 3] == 13
    assert (s["occ_semantics"] == 15).sum() == 200 * 200 * 16 - 1
    assert s["occ_mask_camera"].all() and len(s["render_targets"]) == 5
    # camera 1 is CAM_FRONT_LEFT's images (colour encodes the camera index 2)
    rgb = s["images"][0, 1].float().mean(dim=(0, 1))
    torch.testing.assert_close(rgb, torch.tensor(colour(12, 2), dtype=torch.float32), rtol=0, atol=3.0)
    assert OccDataset(world, waymo_cfg)[0]["occ_semantics"].unique().tolist() == [15]
    with pytest.raises(ValueError, match="the data is waymo.*dataset='nuscenes'"):
        OccDataset(world, cfg().replace(num_cams=5))   # a nuScenes model on Waymo labels
