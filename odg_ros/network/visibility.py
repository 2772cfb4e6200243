"""Which voxels the cameras observe, from the predicted grid: free / occupied / unknown.

A voxel is observed when a camera sees it: its centre projects into a camera's image, it
lies no farther along its own ray than the first predicted surface there (plus half a voxel
diagonal, as Occ3D's ``mask_camera`` allows), and the ray is clear up to it with a probability
of at least ``min_clear``. Everything else is unknown: outside every image, behind a predicted
surface, or behind space the grid calls free where it too often misses an occluder.

That probability comes from a hazard per voxel (``network/calibration.py``, fitted on training
worlds against their ``mask_camera``): how likely a ray through a voxel the grid calls free is
stopped there by something the grid missed, per voxel length of the ray. A ray is clear up to
a distance with probability exp(-optical depth), the hazard summed along it; the voxels beyond
the point where that falls below ``min_clear`` are not seen. Without a hazard (a checkpoint
with no calibration) or with ``min_clear`` 0 only the predicted surfaces hide anything.

Computed on the device with static shapes and no host read, as part of the online step:

1. occluders: the occupied voxels and the stray ones, free in the grid but holding a point
   the grid drops for lying far from its query's centroid (the model put something there:
   on the dense training worlds 42 % of them are truly occupied, against 1.4 % of the free
   voxels seen); a voxel on a flat surface (its two neighbours along exactly one axis are
   not occupied: the road, a wall) occludes at its mid-plane across that axis, one on a
   thin line (a pole) as a thin cylinder along it, any other (edges, lone voxels) as a
   ball about its centre (the surface passes somewhere inside a voxel: its whole box would
   hide too much behind thin things);
2. a depth map per camera over azimuth x elevation cells covering its image (the rows
   dense near the horizon, where the far voxels are): the rays of one azimuth lie in one
   vertical plane, so the grid is read once per column of voxels along it and each ray
   only picks its layer; every ray is sampled about once a voxel, and its first occluder
   gives the cell's depth and, for a mid-plane, that plane; the optical depth along the ray
   gives the cell's second depth, where the ray stops being clear enough;
3. each voxel column is given the camera it projects nearest the image centre of; a voxel
   is observed when its centre is inside that camera's image and not behind the occluder
   of the cell it falls in: for a plane, the voxel's own ray must not cross that plane
   before it (the tangent-plane test of the synthetic ground truth: without it a ray
   grazing the road would hide the road behind the first metre of it), else it must not
   lie beyond the cell's depth; and never beyond the cell's second depth.

Its share of the node's CPU step: ``odg bench --shares`` (odg_ros/bench/stage_shares.py).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from ..preprocess import image_bounds  # noqa: F401  (the bounds the step reads)
from .uint8_compare import is_not, uint8_below, uint8_equals

# occluder kinds: 0 / 1 / 2 the mid-plane across that axis, 3 / 4 / 5 the line through the
# centre along that axis, BALL about the centre, FREE none
LINE, BALL, FREE = 3, 6, 7
# Chosen on the synthetic val split against its mask_camera (tools/visibility_agreement.py):
# depth map cells per camera (rows of elevation, columns of azimuth), the rows uniform in
# log1p(|tan(elevation)| / HORIZON) (signed), so most of them lie near the horizon, where the
# far voxels are; in voxels: the radius of a ball occluder, how far behind a sample a plane's
# crossing may lie, and the horizontal distance between samples; the occluder tests run on
# WINDOW samples from the first occupied one, up to CANDIDATES times along a ray.
# BALL_RADIUS is the inscribed sphere's, 0.5: precision first. The surface lies somewhere in
# the voxel, and most of what even the ground-truth grid calls seen but mask_camera hides
# lies behind an edge or corner voxel; 0.35 hid less (dense traffic, true grid: observed
# precision 0.90 against 0.96, recall 0.83 against 0.78; docs/node.md).
CELLS = (24, 64)
HORIZON = 0.03
BALL_RADIUS, PLANE_REACH, STEP = 0.5, 0.75, 1.0
CANDIDATES, WINDOW = 3, 6
# one ray of the optical depth for every CLEAR_SUBSAMPLE x CLEAR_SUBSAMPLE cells
CLEAR_SUBSAMPLE = 2
# the node's visibility_min_clear: precision first, the lowest whose "observed" precision on
# the calibration's training worlds reaches 0.95 (odg export --calibrate reports it; held-out
# figures per scene class in docs/results/planner.md)
DEFAULT_MIN_CLEAR = 0.85


def _kind_table() -> list[int]:
    """Occluder kind by a 4-bit code: bit a (a = 0, 1, 2) set when both neighbours along
    axis a are not occupied, bit 3 set when the voxel itself is not occupied."""
    table = []
    for code in range(16):
        open_axes = [a for a in range(3) if code >> a & 1]
        if code & 8:
            table.append(FREE)
        elif len(open_axes) == 1:                    # a plane across the one open axis
            table.append(open_axes[0])
        elif len(open_axes) == 2:                    # a line along the closed axis
            table.append(LINE + 3 - sum(open_axes))
        else:
            table.append(BALL)
    return table


class Visibility(nn.Module):
    """observed uint8 [X*Y*Z] (1 = a camera sees the voxel) from the predicted labels and,
    optionally, a missed-occupancy hazard per voxel.

    min_clear: the least probability that a voxel's ray is clear for it to count as seen
    (in [0, 1); 0: the predicted surfaces alone decide); higher trades recall for
    precision."""

    def __init__(self, grid_shape, pc_range, voxel_size: float, free_label: int,
                 min_clear: float = DEFAULT_MIN_CLEAR, cells=CELLS, horizon: float = HORIZON,
                 device="cpu"):
        super().__init__()
        if not 0.0 <= float(min_clear) < 1.0:
            raise ValueError(f"min_clear {min_clear}: expected a probability in [0, 1)")
        self.grid_shape = tuple(int(s) for s in grid_shape)
        self.voxel = float(voxel_size)
        self.free_label = int(free_label)
        self.min_clear = float(min_clear)
        # the optical depth (in voxel lengths x hazard) past which a ray is not clear enough
        self.max_optical_depth = -math.log(self.min_clear) if self.min_clear > 0 else math.inf
        self.cells = tuple(int(v) for v in cells)
        self.horizon = float(horizon)
        self.tolerance = self.voxel * math.sqrt(3.0) / 2.0      # half a voxel diagonal
        low = torch.tensor(pc_range[:3], dtype=torch.float32)
        high = torch.tensor(pc_range[3:], dtype=torch.float32)
        # horizontal samples (voxels) as far as the grid reaches from a camera up to 4 m from
        # the ego frame's origin
        farthest = torch.maximum(low.abs(), high.abs())[:2]
        reach = (float(torch.linalg.vector_norm(farthest)) + 4.0) / self.voxel
        samples = int(math.ceil(reach / STEP))
        if self.grid_shape[2] + 2 > 31:       # a column's occupied layers: bits of an int32
            raise ValueError(f"{self.grid_shape[2]} layers: at most 29 are supported")
        self.register_buffer("low", low.to(device), persistent=False)
        self.register_buffer("ranges", ((torch.arange(samples, dtype=torch.float32) + 0.5)
                                        * STEP).to(device), persistent=False)
        self.register_buffer("layer_bits", 2 ** torch.arange(self.grid_shape[2] + 2,
                                                             dtype=torch.int32, device=device),
                             persistent=False)
        # row first * (Z + 1) + last + 1: the layers first..last (first in 0..Z, last in
        # -1..Z - 1)
        layer = torch.arange(self.grid_shape[2], device=device)
        bounds = torch.arange(-1, self.grid_shape[2] + 1, device=device)
        self.register_buffer("layer_ranges", ((layer >= bounds[1:, None, None])
                                              & (layer <= bounds[None, :-1, None]))
                             .view(-1, self.grid_shape[2]), persistent=False)
        self.register_buffer("kind_table", torch.tensor(_kind_table(), dtype=torch.uint8,
                                                        device=device), persistent=False)
        for axis, name in enumerate("xyz"):
            centres = (torch.arange(self.grid_shape[axis], dtype=torch.float32) + 0.5) \
                * self.voxel + float(pc_range[axis])
            self.register_buffer(f"centre_{name}", centres.to(device), persistent=False)
        self.middle_z = 0.5 * (float(pc_range[2]) + float(pc_range[5]))

    # ----------------------------------------------------------------------- occluders
    def occluders(self, labels: torch.Tensor, stray: torch.Tensor | None = None) -> torch.Tensor:
        """uint8 [X, Y, Z] of occluder kinds: a voxel whose neighbours on both sides are
        not occupied along exactly one axis is a plane across it (the road, a wall), along
        exactly two a line along the third (a pole), else a ball. ``stray`` bool [X*Y*Z]:
        voxels that occlude as if occupied (the grid's stray points, postprocess.py)."""
        free = is_not(labels, self.free_label) ^ 1
        if stray is not None:
            free &= (~stray).to(torch.uint8)
        free = free.view(self.grid_shape)
        padded = nn.functional.pad(free, (1, 1, 1, 1, 1, 1), value=1)
        inner = (slice(1, -1),) * 3
        code = free * 8
        for axis in range(3):
            before, after = list(inner), list(inner)
            before[axis], after[axis] = slice(None, -2), slice(2, None)
            # both neighbours free: their product is 1
            code += padded[tuple(before)] * padded[tuple(after)] * (1 << axis)
        return self.kind_table.index_select(0, code.view(-1).int()).view(self.grid_shape)

    # ------------------------------------------------------------------ camera cells
    def camera_cells(self, img2ego: torch.Tensor, bounds: torch.Tensor):
        """Per camera [N]: its centre [N, 3], the azimuth (rad) of its image centre, and the
        first azimuth offset, the first warped tan(elevation) and the cell sizes of its
        depth map (the image's corners, edge midpoints and centre, with half a cell to
        spare). A camera whose geometry is not finite gets finite stand-ins (its image then
        holds no voxel: visibility.in_image compares against NaN)."""
        u0, v0, u1, v1 = bounds.unbind(-1)
        um, vm = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
        us = torch.stack([u0, um, u1, u0, um, u1, u0, um, u1], -1)             # [N, 9]
        vs = torch.stack([v0, v0, v0, vm, vm, vm, v1, v1, v1], -1)
        ones = torch.ones_like(us)
        points = torch.stack([us, vs, ones, ones], -1) @ img2ego.transpose(1, 2)
        origin = img2ego[:, :3, 3]
        direction = points[..., :3] - origin[:, None]
        centre = torch.atan2(direction[:, 4, 1], direction[:, 4, 0])          # [N]
        azimuth = torch.atan2(direction[..., 1], direction[..., 0]) - centre[:, None]
        azimuth = torch.remainder(azimuth + math.pi, 2 * math.pi) - math.pi
        horizontal = torch.linalg.vector_norm(direction[..., :2], dim=-1).clamp(min=1e-6)
        tangent = self.warp(direction[..., 2] / horizontal)
        rows, columns = self.cells
        first_az, last_az = azimuth.amin(-1), azimuth.amax(-1)
        first_tan, last_tan = tangent.amin(-1), tangent.amax(-1)
        az_size = ((last_az - first_az) / (columns - 1)).clamp(min=1e-6)
        tan_size = ((last_tan - first_tan) / (rows - 1)).clamp(min=1e-6)
        cells = (origin, centre, first_az - 0.5 * az_size, az_size,
                 first_tan - 0.5 * tan_size, tan_size)
        return tuple(torch.nan_to_num(c, nan=1.0, posinf=1.0, neginf=1.0) for c in cells)

    def warp(self, tangent: torch.Tensor) -> torch.Tensor:
        """tan(elevation) -> the coordinate the depth map's rows are uniform in: dense near
        the horizon, logarithmic away from it."""
        return torch.sign(tangent) * torch.log1p(tangent.abs() * (1.0 / self.horizon))

    def unwarp(self, row: torch.Tensor) -> torch.Tensor:
        return torch.sign(row) * torch.expm1(row.abs()) * self.horizon

    # -------------------------------------------------------------------- depth maps
    def rays(self, origin, centre, first_az, az_size, first_tan, tan_size, subsample=1):
        """The rays of the depth maps' cells, sampled about once a voxel: per camera
        [N], the horizontal direction of each azimuth [N, A] (x, y), the tan(elevation) of each
        row [N, E], the column of voxels (flat index into the grid padded by one voxel) under
        each sample of each azimuth [N, A, S] and the layer each row's ray is in there
        [N, E, S] (padding: outside the grid), and the sample's place in its voxel (from the
        voxel's centre, in voxels: [N, A, S] x 2, [N, E, S]). ``subsample`` k: one ray for
        every k x k cells, through their common corner."""
        X, Y, Z = self.grid_shape
        rows, columns = self.cells
        device = origin.device
        first = 0.5 * (subsample - 1)
        azimuth = centre[:, None] + first_az[:, None] + az_size[:, None] * (
            torch.arange(columns // subsample, device=device) * subsample + first + 0.5)
        hx, hy = torch.cos(azimuth), torch.sin(azimuth)                            # [N, A]
        tan = self.unwarp(first_tan[:, None] + tan_size[:, None] * (
            torch.arange(rows // subsample, device=device) * subsample + first + 0.5))
        r = self.ranges                                                        # [S] voxels
        start = (origin - self.low) / self.voxel
        px = start[:, 0, None, None] + hx[..., None] * r
        py = start[:, 1, None, None] + hy[..., None] * r
        pz = start[:, 2, None, None] + tan[..., None] * r
        ix, iy, iz = (p.floor() for p in (px, py, pz))
        column = ((ix.clamp(-1, X) + 1) * (Y + 2) + (iy.clamp(-1, Y) + 1)).long()
        layer = (iz.clamp(-1, Z) + 1).long()
        return hx, hy, tan, column, layer, (px - ix - 0.5, py - iy - 0.5, pz - iz - 0.5)

    @staticmethod
    def along_rays(per_voxel, column, layer):
        """[(X+2)*(Y+2), Z+2] values of the padded grid -> the value at every sample of every
        ray [N, A, E, S]: the column under each sample once per azimuth, then each ray's
        layer in it (broadcast views: no index tensor written)."""
        N, A, S = column.shape
        E, Z2 = layer.shape[1], per_voxel.shape[1]
        under = per_voxel.index_select(0, column.view(-1)).view(N, A, S, Z2)
        return under[:, :, None].expand(N, A, E, S, Z2).gather(
            -1, layer[:, None, :, :, None].expand(N, A, E, S, 1))[..., 0]

    def depth_maps(self, kind, origin, centre, first_az, az_size, first_tan, tan_size):
        """Per camera and cell [N, rows, columns]: the depth along the ray (m, inf: no
        occluder), the occluder's kind (FREE: none) and the plane's coordinate minus the
        camera's along the plane's axis (m).

        Every ray is sampled about once a voxel, but only whether a sample is in an
        occupied voxel (a bit of its column's mask); the occluder tests run on WINDOW
        samples from the first occupied one, then from the first after that window if none
        hit, CANDIDATES times."""
        Z = self.grid_shape[2]
        hx, hy, tan, column, layer, place = self.rays(origin, centre, first_az, az_size,
                                                      first_tan, tan_size)
        padded = nn.functional.pad(kind, (1, 1, 1, 1, 1, 1), value=FREE)
        stacks = padded.view(-1, Z + 2)
        N, A, E, S = len(origin), hx.shape[1], tan.shape[1], self.ranges.shape[0]
        # whether each sample is in an occupied voxel: a bit (its layer) of its column's mask,
        # read once per azimuth; then the occupied samples up to each
        # (multiplications and a bitwise and: ONNX has no shift of int32)
        masks = is_not(stacks, FREE).int().mul_(self.layer_bits).sum(-1, dtype=torch.int32)
        under = masks.index_select(0, column.view(-1)).view(N, A, 1, S)
        bit = self.layer_bits.index_select(0, layer.view(-1)).view(N, 1, E, S)
        # 0 or the layer's bit -> 0 or 1 (int32: ONNX sums no uint8)
        occupied = (under & bit).clamp_(max=1)                                  # [N, A, E, S]
        # counts up to S fit int16, whose running sum and searches take half the time of
        # int32's on the CPU (ONNX's CumSum has no int16: int32 in an export)
        counting = torch.int32 if torch.onnx.is_in_onnx_export() else torch.int16
        count = occupied.cumsum(-1, dtype=counting)
        window = torch.arange(WINDOW, device=kind.device)
        norm = torch.sqrt(1 + tan * tan)                     # ray length per horizontal unit
        geometry = (stacks, column, layer, place, hx, hy, tan, norm)
        # the windows of every ray: from its next occupied sample (S: none) after the end of
        # the window before; they depend on the occupied samples only, so all are tested at
        # once (one pass of the tests over CANDIDATES x WINDOW samples)
        seen = torch.zeros((N, A, E, 1), dtype=counting, device=kind.device)
        windows, exists = [], []
        for _ in range(CANDIDATES):
            entry = torch.searchsorted(count, seen + 1)                       # [N, A, E, 1]
            at = (entry + window).clamp(max=S - 1)                            # [N, A, E, W]
            windows.append(at)
            exists.append((entry < S).expand(N, A, E, WINDOW))
            seen = count.gather(-1, at[..., -1:])
        at = torch.cat(windows, -1)
        hit = self._occluder_tests(at, *geometry)[0] & torch.cat(exists, -1)
        pending = ~hit.any(-1)
        # argmax of int32, not uint8: Inductor's CPU kernels (torch 2.13) reduce a uint8
        # argmax over more lanes than they hold indices for, and read garbage indices
        at_hit = at.gather(-1, hit.to(torch.int32).argmax(-1, keepdim=True))
        # the first hit of every ray again, with its distance, kind and plane
        _, along, k, plane = self._occluder_tests(at_hit, *geometry, full=True)
        hit = ~pending
        depth = torch.where(hit, along[..., 0] * self.voxel,
                            torch.full_like(along[..., 0], float("inf")))
        hit_kind = torch.where(hit, k[..., 0], torch.full_like(k[..., 0], FREE))
        plane = plane[..., 0] * self.voxel
        # [N, A, E] -> [N, E, A]: rows of elevation
        return depth.transpose(1, 2), hit_kind.transpose(1, 2), plane.transpose(1, 2)

    def clear_depths(self, hazard, cells):
        """[N, rows, columns]: per cell, the depth along its ray (m) past which the ray is
        clear with a probability below ``min_clear`` (inf: never), from the hazard [X, Y, Z]
        (per voxel length); one ray for every 2 x 2 cells (the hazard varies slowly)."""
        Z = self.grid_shape[2]
        _, _, tan, column, layer, _ = self.rays(*cells, subsample=CLEAR_SUBSAMPLE)
        rates = nn.functional.pad(hazard.view(self.grid_shape), (1, 1, 1, 1, 1, 1))
        optical = self.along_rays(rates.view(-1, Z + 2), column, layer).cumsum(-1)
        # a sample stands for STEP x norm voxel lengths of its ray
        norm = torch.sqrt(1 + tan * tan)                                            # [N, E]
        limit = (self.max_optical_depth / (STEP * norm))[:, None, :, None]      # [N, 1, E, 1]
        S = self.ranges.shape[0]
        clear = (optical <= limit).sum(-1, dtype=torch.int32)     # samples still clear
        last = self.ranges[clear.clamp(max=S - 1).long()]
        depth = torch.where(clear < S, last * norm[:, None] * self.voxel,
                            torch.full_like(optical[..., 0], float("inf")))
        k = CLEAR_SUBSAMPLE
        N, A, E = depth.shape                                  # -> every cell of the map
        return depth.transpose(1, 2)[:, :, None, :, None].expand(N, E, k, A, k).reshape(
            N, E * k, A * k)

    def _occluder_tests(self, at, stacks, column, layer, place, hx, hy, tan, norm,
                        full=False):
        """The occluder test of samples ``at`` [N, A, E, W] of every ray -> (hit, and with
        ``full``: the distance along the ray to it, its kind, the plane's coordinate minus
        the camera's; voxels)."""
        N, A, E, W = at.shape
        along_a = at.reshape(N, A, E * W)
        along_e = at.transpose(1, 2).reshape(N, E, A * W)

        def per_azimuth(values):                  # [N, A, S] -> [N, A, E, W]
            return values.gather(-1, along_a).view(N, A, E, W)

        def per_elevation(values):                # [N, E, S] -> [N, A, E, W]
            return values.gather(-1, along_e).view(N, E, A, W).transpose(1, 2)

        x, y, z = per_azimuth(place[0]), per_azimuth(place[1]), per_elevation(place[2])
        voxel = per_azimuth(column) * stacks.shape[1] + per_elevation(layer)
        k = stacks.view(-1).index_select(0, voxel.view(-1)).view(N, A, E, W)
        h_x, h_y = hx[..., None, None], hy[..., None, None]
        tn, n = tan[:, None, :, None], norm[:, None, :, None]
        # mid-plane: the horizontal distance back to where the ray crosses it
        plane_of = [uint8_equals(k, a) for a in range(3)]
        direction = torch.where(plane_of[0], h_x, torch.where(plane_of[1], h_y, tn))
        direction = torch.where(direction.abs() > 1e-6, direction,
                                torch.full_like(direction, 1e-6))
        offset = torch.where(plane_of[0], x, torch.where(plane_of[1], y, z))
        back = offset / direction
        on_plane = uint8_below(k, LINE) & (back * n <= PLANE_REACH)
        # ball: the distance of the voxel centre from the ray, |place x direction|; line:
        # from the line through the centre along axis a, (place x direction)_a / |e_a x d|
        d = (h_x / n, h_y / n, tn / n)
        cross = (y * d[2] - z * d[1], z * d[0] - x * d[2], x * d[1] - y * d[0])
        is_ball = uint8_equals(k, BALL)
        ball = is_ball.float()
        miss = 0.0
        for a in range(3):
            weight = torch.where(uint8_equals(k, LINE + a),
                                 1.0 / (1.0 - d[a] * d[a]).clamp(min=1e-12), ball)
            miss = miss + weight * cross[a] * cross[a]
        on_ball = ~uint8_below(k, LINE) & uint8_below(k, FREE) & (miss <= BALL_RADIUS ** 2)
        hit = on_plane | on_ball
        if not full:
            return hit, None, None, None
        t = self.ranges[at]                                               # horizontal
        ahead = -(x * h_x + y * h_y + z * tn) / n
        along = torch.where(on_plane, (t - back) * n, t * n + ahead)
        plane = torch.where(plane_of[0], h_x * t - x,
                            torch.where(plane_of[1], h_y * t - y, tn * t - z))
        return hit, along, k, plane

    # ---------------------------------------------------------------------- voxel test
    def column_cameras(self, ego2img: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        """long [X, Y]: per voxel column, the camera its centre (at the grid's middle
        height) projects nearest the image centre of (horizontally)."""
        # one camera at a time on contiguous [X, Y] tensors (an [X, Y, N] camera axis
        # broadcasts: several times slower on the CPU), the nearest kept as it goes (the
        # first on a tie, as argmin picks)
        cx, cy = self.centre_x[:, None], self.centre_y[None, :]
        middle = 0.5 * (bounds[:, 0] + bounds[:, 2])
        half = 0.5 * (bounds[:, 2] - bounds[:, 0])
        nearest = camera = None
        for n, e in enumerate(ego2img.unbind(0)):
            u = e[0, 0] * cx + e[0, 1] * cy + (e[0, 2] * self.middle_z + e[0, 3])  # [X, Y]
            z = e[2, 0] * cx + e[2, 1] * cy + (e[2, 2] * self.middle_z + e[2, 3])
            off_centre = (u - middle[n] * z).abs() / (half[n] * z.clamp(min=1e-3))
            off_centre = torch.where(z > 1e-3, off_centre, torch.full_like(off_centre, 1e9))
            off_centre = torch.nan_to_num(off_centre, nan=1e9)
            if camera is None:
                nearest, camera = off_centre, torch.zeros_like(off_centre, dtype=torch.long)
                continue
            camera = torch.where(off_centre < nearest, n, camera)
            nearest = torch.minimum(nearest, off_centre)
        return camera

    def forward(self, labels: torch.Tensor, ego2img: torch.Tensor, img2ego: torch.Tensor,
                bounds: torch.Tensor, hazard: torch.Tensor | None = None,
                stray: torch.Tensor | None = None) -> torch.Tensor:
        """labels [X*Y*Z] (free_label = free); ego2img, img2ego [N, 4, 4] of the current set
        (ego frame -> image pixels x depth, and back); bounds [N, 4] (u0, v0, u1, v1) of each
        image in those pixels; hazard [X*Y*Z] float or None (network/calibration.py); stray
        bool [X*Y*Z] or None: free voxels that occlude too (postprocess.stray_voxels) ->
        observed uint8 [X*Y*Z]."""
        X, Y, Z = self.grid_shape
        kind = self.occluders(labels, stray)
        cells = self.camera_cells(img2ego, bounds)
        beyond, normal = self.bordered_maps(kind, hazard, cells)      # [M], [3, M]
        inside, cell, distance, (dx, dy, dz) = self.voxel_cells(ego2img, bounds, cells)
        # behind the cell's mid-plane: the voxel's own ray crosses it (at this fraction of
        # its length) more than the tolerance before the voxel; with the plane's normal
        # scaled by 1 / (its offset from the camera), normal . ray = 1 / fraction, and a
        # ray running away from the plane or along it does not cross it (<= 0). Behind
        # its ball or line, or where the ray is not clear enough: beyond the cell's depth.
        # (one axis at a time: a gather along the second dimension of [3, M] runs
        # element by element; in place where a result is fresh: every [X, Y, Z] tensor
        # allocated costs)
        n = [normal[a].index_select(0, cell).view(X, Y, Z) for a in range(3)]
        inverse = (n[0] * dx).addcmul_(n[1], dy).addcmul_(n[2], dz).view(-1)
        # (a voxel nearer than the tolerance is never behind a plane: clamped to 0, its
        # product is not above its distance, as none is where the ray runs away)
        behind = (distance - self.tolerance).clamp_(min=0).mul_(inverse) > distance
        behind |= distance > beyond.index_select(0, cell)
        return (inside & ~behind).to(torch.uint8)

    def voxel_cells(self, ego2img, bounds, cells):
        """Per voxel, flat [X*Y*Z]: inside its column's camera image (bool), its cell of the
        bordered depth maps (int, [N, rows + 2, columns + 2] flat), its distance from that
        camera (m); and its offset from the camera (m): dx, dy [X, Y, 1], dz [X, Y, Z]."""
        rows, columns = self.cells
        origin, centre, first_az, az_size, first_tan, tan_size = cells
        camera = self.column_cameras(ego2img, bounds)                       # [X, Y]
        inside = self.in_image(ego2img, bounds, camera).view(-1)
        # per column [X, Y, 1]: its camera's centre, the horizontal distance and the
        # azimuth cell (a column of the bordered map: 0 and columns + 1 are outside)
        def per_column(values):                  # [N] -> its column's camera's [X, Y, 1]
            return values.index_select(0, camera.view(-1)).view(*camera.shape, 1)
        o = [per_column(origin[:, a]) for a in range(3)]
        dx = self.centre_x[:, None, None] - o[0]
        dy = self.centre_y[None, :, None] - o[1]
        squared = dx * dx + dy * dy
        horizontal = torch.sqrt(squared).clamp(min=1e-3)
        offset = torch.remainder(torch.atan2(dy, dx) - per_column(centre) + math.pi,
                                 2 * math.pi) - math.pi
        a = ((offset - per_column(first_az)) / per_column(az_size)).floor()
        # the map's first row (the border above is row 0) of this column
        base = camera[..., None] * ((rows + 2) * (columns + 2)) + a.clamp(-1, columns) + 1 \
            + (columns + 2)
        per_row = 1.0 / per_column(tan_size)
        # per voxel [X, Y, Z] (in place where a result is fresh): its row (warped elevation,
        # as ``warp`` with the divisions done per column), cell and distance
        dz = self.centre_z - o[2]
        row = dz.abs().mul_(1.0 / (self.horizon * horizontal)).log1p_().mul_(torch.sign(dz))
        row = row.mul_(per_row).sub_(per_column(first_tan) * per_row).floor_()
        cell = row.clamp_(-1, rows).mul_(columns + 2).add_(base).int().view(-1)
        distance = (dz * dz).add_(squared).sqrt_().view(-1)
        return inside, cell, distance, (dx, dy, dz)

    def optical_paths(self, rates, ego2img, img2ego, bounds, voxels, chunk: int = 8):
        """What ``min_clear`` is tested against, per hazard: rates [K, X, Y, Z] (K hazards,
        per voxel length), voxels long [V] -> [V, K], the optical depth of each hazard along
        each voxel's ray up to it (the voxel is hidden when the sum over the hazards exceeds
        -log(min_clear)). For fitting a hazard (train/calibrate.py); the voxels must lie in a
        cell of a map (not on its border)."""
        rows, columns = self.cells
        k, S, Z = CLEAR_SUBSAMPLE, self.ranges.shape[0], self.grid_shape[2]
        cells = self.camera_cells(img2ego, bounds)
        _, _, tan, column, layer, _ = self.rays(*cells, subsample=k)
        _, cell, distance, _ = self.voxel_cells(ego2img, bounds, cells)
        cell, distance = cell.long()[voxels], distance[voxels]
        camera, rest = cell // ((rows + 2) * (columns + 2)), cell % ((rows + 2) * (columns + 2))
        row, col = rest // (columns + 2) - 1, rest % (columns + 2) - 1
        if bool(((row < 0) | (row >= rows) | (col < 0) | (col >= columns)).any()):
            raise ValueError("optical_paths: a voxel outside every depth map")
        norm = torch.sqrt(1 + tan * tan)[camera, row // k]                           # [V]
        length = STEP * norm * self.voxel          # metres of ray a sample stands for
        # the samples wholly before the voxel (as clear_depths: r norm voxel + tolerance)
        before = torch.ceil((distance - self.tolerance) / length - 0.5).clamp(0, S).long()
        where = ((camera * (columns // k) + col // k) * (rows // k) + row // k) * (S + 1) \
            + before
        out = []
        for start in range(0, len(rates), chunk):
            part = nn.functional.pad(rates[start:start + chunk], (1, 1, 1, 1, 1, 1))
            sums = torch.stack([self.along_rays(p.reshape(-1, Z + 2), column, layer)
                                for p in part], -1).cumsum(-2)          # [N, A, E, S, k]
            sums = nn.functional.pad(sums, (0, 0, 1, 0))               # nothing passed: 0
            out.append(sums.reshape(-1, sums.shape[-1])[where] * (STEP * norm)[:, None])
        return torch.cat(out, -1)

    def in_image(self, ego2img, bounds, camera) -> torch.Tensor:
        """bool [X, Y, Z]: the voxel centres inside the image of their column's camera
        (``ego2img`` [N, 4, 4], ``bounds`` [N, 4], ``camera`` long [X, Y]); NaN geometry
        sees nothing."""
        e = ego2img[:, :3]                                                    # [N, 3, 4]
        # each image edge as a plane through the camera, its normal pointing inwards:
        # u >= u0 w, v >= v0 w, u < u1 w, v < v1 w (the strict ones last; u0 and u1 also
        # put it in front: they add up to (u1 - u0) w > 0)
        b = bounds[:, :, None]
        edges = torch.stack([e[:, 0] - b[:, 0] * e[:, 2], e[:, 1] - b[:, 1] * e[:, 2],
                             b[:, 2] * e[:, 2] - e[:, 0], b[:, 3] * e[:, 2] - e[:, 1]], 0)
        # one edge at a time, on [X, Y] tensors of the column's camera's plane (a flat
        # gather each: an [X, Y, 4] edge axis costs several times more, strided)
        flat = camera.view(-1)
        lowest = highest = None
        big = 1e6
        for i, edge in enumerate(edges.unbind(0)):
            x, y, slope, constant = (edge[:, j].index_select(0, flat).view(camera.shape)
                                     for j in range(4))
            # along a column, the edge is linear in the height: inside on one side of the
            # layer where it crosses 0, so the image holds a range of layers [lowest,
            # highest]
            at_column = x * self.centre_x[:, None] + y * self.centre_y + constant
            crossing = torch.nan_to_num((-at_column / slope - self.centre_z[0]) / self.voxel,
                                        nan=0.0, posinf=big, neginf=-big)      # in layers
            # rising (slope > 0): the layers k >= crossing (k > crossing for the strict
            # edges u1, v1); falling: k <= crossing (k <); level (or NaN): all of them or
            # none (masks and sums, not selects: cheaper)
            strict = i >= 2
            up = torch.floor(crossing) + 1 if strict else torch.ceil(crossing)
            down = torch.ceil(crossing) - 1 if strict else torch.floor(crossing)
            rising, falling = (slope > 0).float(), (slope < 0).float()
            level = 1 - rising - falling
            none = big * (1 - 2 * (at_column > 0).float())       # level: none unless inside
            low = rising * up - falling * big + level * none
            high = falling * down + rising * big - level * none
            lowest = low if lowest is None else torch.maximum(lowest, low)
            highest = high if highest is None else torch.minimum(highest, high)
        # the layers k in [lowest, highest]: k in [ceil(lowest), floor(highest)] clamped to
        # the grid (NaN: none), a row of the table of every such range (a comparison per
        # voxel runs element by element on the CPU)
        Z = self.grid_shape[2]
        first = torch.nan_to_num(torch.ceil(lowest), nan=Z).clamp_(0, Z)
        last = torch.nan_to_num(torch.floor(highest), nan=-1).clamp_(-1, Z - 1)
        ranges = (first * (Z + 1) + last + 1).long().view(-1)
        return self.layer_ranges.index_select(0, ranges).view(*camera.shape, Z)

    def bordered_maps(self, kind, hazard, cells):
        """The depth maps as the voxel test reads them, flat over [N, rows + 2, columns + 2]
        (a border of cells around each map, where everything outside it falls): the depth
        beyond which a voxel is hidden (m, the tolerance added; a plane cell's only from a
        ray not clear enough; -inf on the border: never observed) [M], and the normal of a
        plane cell's plane over its offset from the camera (1 / m; 0 elsewhere) [3, M]."""
        depth, hit_kind, plane = self.depth_maps(kind, *cells)
        is_plane = hit_kind < LINE
        depth = torch.where(is_plane, torch.full_like(depth, float("inf")), depth)
        if hazard is not None and math.isfinite(self.max_optical_depth):
            depth = torch.minimum(depth, self.clear_depths(hazard, cells))
        beyond = nn.functional.pad(depth + self.tolerance, (1, 1, 1, 1), value=-float("inf"))
        inverse = torch.where(is_plane & (plane.abs() > 1e-6), 1.0 / plane,
                              torch.zeros_like(plane))
        normal = torch.stack([torch.where(hit_kind == a, inverse, torch.zeros_like(inverse))
                              for a in range(3)])                             # [3, N, E, A]
        normal = nn.functional.pad(normal, (1, 1, 1, 1))
        return beyond.reshape(-1), normal.reshape(3, -1)
