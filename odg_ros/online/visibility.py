"""Which voxels the cameras observe, from the predicted grid: free / occupied / unknown.

A voxel is observed when a camera sees it: its centre projects into a camera's image and
lies no farther along its own ray than the first predicted surface there (plus half a
voxel diagonal, as Occ3D's ``mask_camera`` allows). Everything else is unknown: outside
every image, or behind a predicted surface.

Computed on the device with static shapes and no host read, as part of the online step:

1. occluders: a voxel on a flat surface (its two neighbours along exactly one axis are
   not occupied: the road, a wall) occludes at its mid-plane across that axis, one on a
   thin line (a pole) as a thin cylinder along it, any other (edges, lone voxels) as a
   ball about its centre (the surface passes somewhere inside a voxel: its whole box would
   hide too much behind thin things);
2. a depth map per camera over azimuth x elevation cells covering its image (the rows
   dense near the horizon, where the far voxels are): the rays of one azimuth lie in one
   vertical plane, so the grid is read once per column of voxels along it and each ray
   only picks its layer; every ray is sampled about once a voxel, and its first occluder
   gives the cell's depth and, for a mid-plane, that plane;
3. each voxel column is given the camera it projects nearest the image centre of; a voxel
   is observed when its centre is inside that camera's image and not behind the occluder
   of the cell it falls in: for a plane, the voxel's own ray must not cross that plane
   before it (the tangent-plane test of the synthetic ground truth: without it a ray
   grazing the road would hide the road behind the first metre of it), else it must not
   lie beyond the cell's depth.

On odg_cpu's grid it takes about a sixth of the CPU step (one thread; the measurement:
tools/visibility_agreement.py --step-share).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from ..preprocess import image_bounds  # noqa: F401  (the bounds the step reads)

# occluder kinds: 0 / 1 / 2 the mid-plane across that axis, 3 / 4 / 5 the line through the
# centre along that axis, BALL about the centre, FREE none
LINE, BALL, FREE = 3, 6, 7
# Chosen on the synthetic val split against its mask_camera (tools/visibility_agreement.py):
# depth map cells per camera (rows of elevation, columns of azimuth), the rows uniform in
# asinh(tan(elevation) / HORIZON), so most of them lie near the horizon, where the far
# voxels are; in voxels: the radius of a ball occluder, how far behind a sample a plane's
# crossing may lie, and the horizontal distance between samples; the occluder tests run on
# WINDOW samples from the first occupied one, up to CANDIDATES times along a ray.
CELLS = (32, 64)
HORIZON = 0.03
BALL_RADIUS, PLANE_REACH, STEP = 0.35, 0.75, 0.9
CANDIDATES, WINDOW = 3, 8
MAX_TAN = 100.0               # steeper rays (straight up or down) count as this steep


class Visibility(nn.Module):
    """observed uint8 [X*Y*Z] (1 = a camera sees the voxel) from the predicted labels."""

    def __init__(self, grid_shape, pc_range, voxel_size: float, free_label: int,
                 cells=CELLS, horizon: float = HORIZON, device="cpu"):
        super().__init__()
        self.grid_shape = tuple(int(s) for s in grid_shape)
        self.voxel = float(voxel_size)
        self.free_label = int(free_label)
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
        self.register_buffer("low", low.to(device), persistent=False)
        self.register_buffer("ranges", ((torch.arange(samples, dtype=torch.float32) + 0.5)
                                        * STEP).to(device), persistent=False)
        for axis, name in enumerate("xyz"):
            centres = (torch.arange(self.grid_shape[axis], dtype=torch.float32) + 0.5) \
                * self.voxel + float(pc_range[axis])
            self.register_buffer(f"centre_{name}", centres.to(device), persistent=False)
        self.middle_z = 0.5 * (float(pc_range[2]) + float(pc_range[5]))

    # ----------------------------------------------------------------------- occluders
    def occluders(self, labels: torch.Tensor) -> torch.Tensor:
        """uint8 [X, Y, Z] of occluder kinds: a voxel whose neighbours on both sides are
        not occupied along exactly one axis is a plane across it (the road, a wall), along
        exactly two a line along the third (a pole), else a ball."""
        occupied = (labels != self.free_label).view(self.grid_shape)
        padded = nn.functional.pad(occupied.to(torch.uint8), (1, 1, 1, 1, 1, 1))
        inner = (slice(1, -1),) * 3
        open_sides = []
        for axis in range(3):
            before, after = list(inner), list(inner)
            before[axis], after[axis] = slice(None, -2), slice(2, None)
            open_sides.append(((padded[tuple(before)] + padded[tuple(after)]) == 0)
                              .to(torch.uint8))
        count = open_sides[0] + open_sides[1] + open_sides[2]
        plane = open_sides[1] + 2 * open_sides[2]
        line = LINE + (1 - open_sides[1]) + 2 * (1 - open_sides[2])
        kind = torch.where(count == 1, plane, torch.where(count == 2, line,
                                                           torch.full_like(plane, BALL)))
        return torch.where(occupied, kind, torch.full_like(plane, FREE))

    # ------------------------------------------------------------------ camera cells
    def camera_cells(self, img2ego: torch.Tensor, bounds: torch.Tensor):
        """Per camera [N]: its centre [N, 3], the azimuth (rad) of its image centre, and the
        first azimuth offset, the first tan(elevation) and the cell sizes of its depth map
        (the image's corners, edge midpoints and centre, with half a cell to spare)."""
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
        tangent = self.warp((direction[..., 2] / horizontal).clamp(-MAX_TAN, MAX_TAN))
        rows, columns = self.cells
        first_az, last_az = azimuth.amin(-1), azimuth.amax(-1)
        first_tan, last_tan = tangent.amin(-1), tangent.amax(-1)
        az_size = ((last_az - first_az) / (columns - 1)).clamp(min=1e-6)
        tan_size = ((last_tan - first_tan) / (rows - 1)).clamp(min=1e-6)
        return origin, centre, first_az - 0.5 * az_size, az_size, \
            first_tan - 0.5 * tan_size, tan_size

    def warp(self, tangent: torch.Tensor) -> torch.Tensor:
        """tan(elevation) -> the coordinate the depth map's rows are uniform in."""
        return torch.asinh(tangent / self.horizon)

    def unwarp(self, row: torch.Tensor) -> torch.Tensor:
        return torch.sinh(row) * self.horizon

    # -------------------------------------------------------------------- depth maps
    def depth_maps(self, kind, origin, centre, first_az, az_size, first_tan, tan_size):
        """Per camera and cell [N, rows, columns]: the depth along the ray (m, inf: no
        occluder), the occluder's kind (FREE: none) and the plane's coordinate minus the
        camera's along the plane's axis (m).

        Every ray is sampled about once a voxel, but only whether a sample is in an
        occupied voxel (a bit of its column's mask); the occluder tests run on WINDOW
        samples from the first occupied one, then from the first after that window if none
        hit, CANDIDATES times."""
        X, Y, Z = self.grid_shape
        rows, columns = self.cells
        device = kind.device
        azimuth = centre[:, None] + first_az[:, None] + az_size[:, None] * (
            torch.arange(columns, device=device) + 0.5)                          # [N, A]
        hx, hy = torch.cos(azimuth), torch.sin(azimuth)
        tan = self.unwarp(first_tan[:, None] + tan_size[:, None] * (
            torch.arange(rows, device=device) + 0.5))                             # [N, E]
        r = self.ranges                                                        # [S] voxels
        start = (origin - self.low) / self.voxel
        # the column of voxels under each sample of each azimuth [N, A, S], and the layer
        # each ray of each elevation is in there [N, E, S]
        px = start[:, 0, None, None] + hx[..., None] * r
        py = start[:, 1, None, None] + hy[..., None] * r
        pz = start[:, 2, None, None] + tan[..., None] * r
        # (nan_to_num: geometry that is no rigid transform reads no voxel, never garbage)
        ix, iy, iz = (torch.nan_to_num(p.floor(), nan=-1.0) for p in (px, py, pz))
        column = ((ix.clamp(-1, X) + 1) * (Y + 2) + (iy.clamp(-1, Y) + 1)).long()
        layer = (iz.clamp(-1, Z) + 1).long()
        padded = nn.functional.pad(kind, (1, 1, 1, 1, 1, 1), value=FREE)
        stacks = padded.view(-1, Z + 2)
        # whether each ray's sample is in an occupied voxel: its layer of the column under
        # it, read through broadcast views (one uint8 gather, no index tensor written)
        N, A, E, S = len(origin), columns, rows, r.shape[0]
        columns_under = (stacks != FREE).to(torch.uint8)[column]             # [N, A, S, Z+2]
        occupied = columns_under[:, :, None].expand(N, A, E, S, Z + 2).gather(
            -1, layer[:, None, :, :, None].expand(N, A, E, S, 1))[..., 0]  # [N, A, E, S]
        count = occupied.cumsum(-1, dtype=torch.int32)   # occupied samples up to each
        window = torch.arange(WINDOW, device=device)
        depth = torch.full((len(origin), columns, rows), float("inf"), device=device)
        hit_kind = torch.full_like(depth, FREE, dtype=kind.dtype)
        plane = torch.zeros_like(depth)
        pending = torch.ones_like(depth, dtype=torch.bool)
        seen = torch.zeros_like(depth, dtype=torch.int32)    # occupied samples passed
        for _ in range(CANDIDATES):
            # the next occupied sample of every ray (S: none), and a window from it
            entry = torch.searchsorted(count, seen[..., None] + 1)[..., 0]   # [N, A, E]
            exists = entry < S
            at = (entry[..., None] + window).clamp(max=S - 1)                 # [N, A, E, W]
            hit, along, k, offset = self._candidate(at, stacks, column, layer, px, py, pz,
                                                    ix, iy, iz, hx, hy, tan, r, start)
            first = hit.to(torch.uint8).argmax(-1, keepdim=True)
            take = pending & exists & hit.any(-1)
            depth = torch.where(take, along.gather(-1, first)[..., 0] * self.voxel, depth)
            hit_kind = torch.where(take, k.gather(-1, first)[..., 0], hit_kind)
            plane = torch.where(take, offset.gather(-1, first)[..., 0] * self.voxel, plane)
            pending = pending & ~take
            seen = count.gather(-1, at[..., -1:])[..., 0]
        # [N, A, E] -> [N, E, A]: rows of elevation
        return depth.transpose(1, 2), hit_kind.transpose(1, 2), plane.transpose(1, 2)

    def _candidate(self, at, stacks, column, layer, px, py, pz, ix, iy, iz, hx, hy, tan, r,
                   start):
        """The occluder test of samples ``at`` [N, A, E, W] of every ray -> (hit, the
        distance along the ray to it, its kind, the plane's coordinate minus the camera's;
        voxels)."""
        N, A, E, W = at.shape
        along_a = at.reshape(N, A, E * W)
        along_e = at.transpose(1, 2).reshape(N, E, A * W)

        def per_azimuth(values):                  # [N, A, S] -> [N, A, E, W]
            return values.gather(-1, along_a).view(N, A, E, W)

        def per_elevation(values):                # [N, E, S] -> [N, A, E, W]
            return values.gather(-1, along_e).view(N, E, A, W).transpose(1, 2)

        x, y, z = per_azimuth(px), per_azimuth(py), per_elevation(pz)
        vx, vy, vz = per_azimuth(ix), per_azimuth(iy), per_elevation(iz)
        k = stacks[per_azimuth(column), per_elevation(layer)]
        fx, fy, fz = x - vx - 0.5, y - vy - 0.5, z - vz - 0.5
        t = r[at]                                                         # horizontal
        h_x, h_y, tn = hx[..., None, None], hy[..., None, None], tan[:, None, :, None]
        norm = torch.sqrt(1 + tn * tn)
        # mid-plane: the horizontal distance back to where the ray crosses it
        direction = torch.where(k == 0, h_x, torch.where(k == 1, h_y, tn))
        direction = torch.where(direction.abs() > 1e-6, direction,
                                torch.full_like(direction, 1e-6))
        offset = torch.where(k == 0, fx, torch.where(k == 1, fy, fz))
        back = offset / direction
        on_plane = (k < LINE) & (back * norm <= PLANE_REACH)
        # ball: the closest approach of the ray to the voxel centre
        ahead = -(fx * h_x + fy * h_y + fz * tn) / norm
        miss = fx * fx + fy * fy + fz * fz - ahead * ahead
        # line: the distance between the ray and the line through the centre along its axis
        d = (h_x / norm, h_y / norm, tn / norm)
        f = (fx, fy, fz)
        line_miss = []
        for a in range(3):
            b, c = (a + 1) % 3, (a + 2) % 3
            across = f[b] * d[c] - f[c] * d[b]
            line_miss.append(across * across / (d[b] * d[b] + d[c] * d[c]).clamp(min=1e-12))
        miss = torch.where(k == LINE, line_miss[0], torch.where(
            k == LINE + 1, line_miss[1], torch.where(k == LINE + 2, line_miss[2], miss)))
        on_ball = (k >= LINE) & (k < FREE) & (miss <= BALL_RADIUS ** 2)
        along = torch.where(on_plane, (t - back) * norm, t * norm + ahead)
        s = start[:, :, None, None, None]
        plane = torch.where(k == 0, vx - s[:, 0], torch.where(k == 1, vy - s[:, 1],
                                                               vz - s[:, 2])) + 0.5
        return on_plane | on_ball, along, k, plane

    # ---------------------------------------------------------------------- voxel test
    def column_cameras(self, ego2img: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        """long [X, Y]: per voxel column, the camera its centre (at the grid's middle
        height) projects nearest the image centre of (horizontally)."""
        cx, cy = self.centre_x[None, :, None], self.centre_y[None, None, :]
        e = ego2img[:, :, :, None, None]                                    # [N, 4, 4, 1, 1]
        u = e[:, 0, 0] * cx + e[:, 0, 1] * cy + (e[:, 0, 2] * self.middle_z + e[:, 0, 3])
        z = e[:, 2, 0] * cx + e[:, 2, 1] * cy + (e[:, 2, 2] * self.middle_z + e[:, 2, 3])
        middle = (0.5 * (bounds[:, 0] + bounds[:, 2]))[:, None, None]
        half = (0.5 * (bounds[:, 2] - bounds[:, 0]))[:, None, None]
        off_centre = (u - middle * z).abs() / (half * z.clamp(min=1e-3))
        off_centre = torch.where(z > 1e-3, off_centre, torch.full_like(off_centre, 1e9))
        return off_centre.argmin(0)

    def forward(self, labels: torch.Tensor, ego2img: torch.Tensor, img2ego: torch.Tensor,
                bounds: torch.Tensor) -> torch.Tensor:
        """labels [X*Y*Z] (free_label = free); ego2img, img2ego [N, 4, 4] of the current set
        (ego frame -> image pixels x depth, and back); bounds [N, 4] (u0, v0, u1, v1) of each
        image in those pixels -> observed uint8 [X*Y*Z]."""
        rows, columns = self.cells
        kind = self.occluders(labels)
        cells = self.camera_cells(img2ego, bounds)
        origin, centre, first_az, az_size, first_tan, tan_size = cells
        depth, plane_axis, plane = (m.reshape(-1) for m in self.bordered_maps(kind, cells))
        camera = self.column_cameras(ego2img, bounds)                       # [X, Y]
        inside = self.in_image(ego2img[camera], bounds[camera])
        # per column [X, Y, 1]: its camera's centre, the horizontal distance and the
        # azimuth cell (a column of the bordered map: 0 and columns + 1 are outside)
        o = origin[camera][..., None]
        dx = self.centre_x[:, None, None] - o[:, :, 0]
        dy = self.centre_y[None, :, None] - o[:, :, 1]
        horizontal = torch.sqrt(dx * dx + dy * dy)
        offset = torch.remainder(torch.atan2(dy, dx) - centre[camera][..., None] + math.pi,
                                 2 * math.pi) - math.pi
        a = torch.nan_to_num(((offset - first_az[camera][..., None])
                              / az_size[camera][..., None]).floor(), nan=-1.0)
        base = camera[..., None] * ((rows + 2) * (columns + 2)) + a.clamp(-1, columns) + 1
        # per voxel [X, Y, Z]: its cell, the distance, the test against the cell's occluder
        dz = self.centre_z[None, None, :] - o[:, :, 2]
        tangent = (dz / horizontal.clamp(min=1e-3)).clamp(-MAX_TAN, MAX_TAN)
        row = torch.nan_to_num((self.warp(tangent) - first_tan[camera][..., None])
                               / tan_size[camera][..., None], nan=-1.0).floor()
        cell = (base + (row.clamp(-1, rows) + 1) * (columns + 2)).long()
        distance = torch.sqrt(horizontal * horizontal + dz * dz)
        # behind the cell's mid-plane: the voxel's own ray crosses it (at this fraction of
        # its length, along the plane's axis) more than the tolerance before the voxel; a
        # ray running away from the plane or along it does not (the fraction is negative,
        # infinite or NaN). Behind its ball or line: farther than its depth.
        axis = plane_axis[cell]
        towards = torch.where(axis == 0, dx, torch.where(axis == 1, dy, dz))
        fraction = plane[cell] / towards
        behind = ((fraction > 0) & (fraction < 1 - self.tolerance / distance)) | \
            (distance > depth[cell] + self.tolerance)
        return (inside & ~behind).view(-1).to(torch.uint8)

    def in_image(self, ego2img, bounds) -> torch.Tensor:
        """bool [X, Y, Z]: the voxel centres inside the image of their column's camera
        (``ego2img`` [X, Y, 4, 4] and ``bounds`` [X, Y, 4] per column)."""
        e, b = ego2img[..., None], bounds[..., None]
        cz = self.centre_z[None, None, :]
        # u, v, depth: the column's part (x, y) once, then the height's
        u, v, w = (torch.addcmul(e[:, :, r, 0] * self.centre_x[:, None, None]
                                 + e[:, :, r, 1] * self.centre_y[None, :, None]
                                 + e[:, :, r, 3], e[:, :, r, 2], cz) for r in range(3))
        return (w > 1e-3) & (u >= b[:, :, 0] * w) & (u < b[:, :, 2] * w) & \
            (v >= b[:, :, 1] * w) & (v < b[:, :, 3] * w)

    def bordered_maps(self, kind, cells):
        """The depth maps [N, rows + 2, columns + 2] as the voxel test reads them: the depth
        of a plane cell infinite and the plane's offset NaN elsewhere (each test reads one of
        them only); the border of cells around the map, where everything outside it falls,
        at depth -inf (never observed)."""
        depth, hit_kind, plane = self.depth_maps(kind, *cells)
        is_plane = hit_kind < LINE
        depth = torch.where(is_plane, torch.full_like(depth, float("inf")), depth)
        plane = torch.where(is_plane, plane, torch.full_like(plane, float("nan")))
        depth = nn.functional.pad(depth, (1, 1, 1, 1), value=-float("inf"))
        return depth, nn.functional.pad(hit_kind, (1, 1, 1, 1), value=FREE), \
            nn.functional.pad(plane, (1, 1, 1, 1), value=float("nan"))
