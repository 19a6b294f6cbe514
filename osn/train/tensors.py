"""The per-object inputs as device tensors, and the device training runs on."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from scenecore.cameras import pixel_rays

from osn.model.fields import Field
from osn.model.volume import ObjectRays
from osn.preprocess.inputs import IGNORE_ID, SceneInputs


def pick_device(name: str = "auto") -> torch.device:
    """CUDA when available (or asked for), else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class SceneTensors:
    """The inputs as device tensors, indexed by object *position* k (``inputs.objects[k]``).

    A training pixel is addressed by its flat index ``frame * H * W + pixel``.

    Attributes:
        images: ``(T, HW, 3)`` float RGB in [0, 1].
        labels: ``(T, HW)`` object position per pixel, -1 where no object.
        dirs: ``(HW, 3)`` camera-frame ray directions with unit z.
        poses: ``(K, T, 4, 4)`` camera-to-object per object and frame (identity where absent).
        present: ``(K, T)`` bool, the object has a pose in the frame.
        t_range: ``(K, 2)`` planar-depth range each object is sampled in (its own unit).
        sp_frame, sp_pix, sp_depth, sp_obj: ``(P,)`` every sparse depth: frame, pixel, depth, object.
        obj_pixels, obj_sparse: per object the flat pixels of its mask / indices of its sparse depths.
        usable: flat pixels not ignored; None when that is every pixel.
        ignored: ``(T * HW,)`` bool, the pixel belongs to a dropped object (``IGNORE_ID``) or to
            an object without a pose in its frame (``unposed_pixels`` of them): no ray is drawn there.
        ranges: ``(K, 2)`` float64 scale range per object (Eq. 1).
    """

    def __init__(self, inputs: SceneInputs, device: torch.device, guide: int = 0) -> None:
        self.inputs = inputs
        self.device = device
        self.guide = int(guide)  # ObjectRays.guide of the anchor's rays (the others' are even)
        T, H, W = inputs.images.shape[:3]
        self.T, self.H, self.W, self.K = T, H, W, inputs.num_objects
        self.images = torch.from_numpy(inputs.images).to(device).float().reshape(T, H * W, 3) / 255.0
        pos_of_id = np.full(256, -1, dtype=np.int64)
        for k, o in enumerate(inputs.objects):
            pos_of_id[o.id] = k
        self.labels = torch.from_numpy(pos_of_id[inputs.masks.reshape(T, H * W)]).to(device)  # -1 = none
        _, d = pixel_rays(inputs.K, np.eye(4), W, H)
        self.dirs = torch.from_numpy(d).float().to(device)  # (HW, 3), camera frame, unit z
        self.anchor = inputs.anchor_pos
        self.poses = torch.eye(4, device=device).repeat(self.K, T, 1, 1)
        self.present = torch.zeros(self.K, T, dtype=torch.bool, device=device)
        self.t_range = torch.zeros(self.K, 2, device=device)  # object-unit planar depth range
        for k, o in enumerate(inputs.objects):
            fr = torch.from_numpy(o.frames).long().to(device)
            self.poses[k, fr] = torch.from_numpy(o.cam_to_obj).float().to(device)
            self.present[k, fr] = True
            self.t_range[k] = torch.tensor([0.5 * o.near, 2.0 * o.far])
        self._sparse_depths(inputs)
        # Per object: flat (frame * HW + pixel) indices of its masked pixels and of its sparse depths.
        flat_labels = self.labels.reshape(-1)
        # Pixels of objects that preprocessing dropped carry no supervision at all (None: every pixel).
        ignored = torch.from_numpy(inputs.masks.reshape(-1) == IGNORE_ID).to(device)
        # A mask pixel of an object in a frame where it has no pose (SfM did not register it
        # there) cannot be rendered by it: such rays would give no gradient, only a constant
        # error, and in composite steps ask the wrong objects to explain the pixel. Left out.
        frame_of = torch.arange(T, device=device).repeat_interleave(H * W)
        has_pose = self.present[flat_labels.clamp_min(0), frame_of] | (flat_labels < 0)
        self.unposed_pixels = int((~has_pose).sum())
        ignored = ignored | ~has_pose
        self.usable = torch.nonzero(~ignored)[:, 0] if bool(ignored.any()) else None
        self.obj_pixels = [torch.nonzero((flat_labels == k) & has_pose)[:, 0] for k in range(self.K)]
        self.ignored = ignored
        self.obj_sparse = [torch.nonzero(self.sp_obj == k)[:, 0] for k in range(self.K)]
        self.ranges = torch.from_numpy(inputs.scale_ranges()).to(device, torch.float64)

    def _sparse_depths(self, inputs: SceneInputs) -> None:
        """Every object's sparse depths as flat ``(P,)`` tensors of frame, pixel, depth and object."""
        sp_frame, sp_pix, sp_depth, sp_obj = [], [], [], []
        for k, o in enumerate(inputs.objects):
            for slot, t in enumerate(o.frames):
                pix, dep = o.sparse_pix[slot], o.sparse_depth[slot]
                if len(dep) == 0:
                    continue
                sp_frame.append(np.full(len(dep), t))
                sp_pix.append(pix[:, 1] * self.W + pix[:, 0])
                sp_depth.append(dep)
                sp_obj.append(np.full(len(dep), k))

        def cat(xs: list[np.ndarray], dt: torch.dtype) -> torch.Tensor:
            return torch.from_numpy(np.concatenate(xs) if xs else np.zeros(0)).to(self.device, dt)

        self.sp_frame, self.sp_pix = cat(sp_frame, torch.long), cat(sp_pix, torch.long)
        self.sp_depth, self.sp_obj = cat(sp_depth, torch.float32), cat(sp_obj, torch.long)

    def free_pixels(self, band: int, object_band: int | None = None,
                    in_front: frozenset[tuple[int, int]] = frozenset(),
                    constrained: frozenset[tuple[int, int]] | None = None) -> list[torch.Tensor]:
        """Per object the flat indices of pixels its field must leave empty, in frames where it
        is present: pixels showing the anchor or nothing within ``band`` pixels of its mask
        (objects are never behind the anchor, e.g. a room that contains them), and, for every
        object but the anchor, other objects' pixels within ``object_band`` pixels of its mask
        (default ``band``), except those of j for object positions ``(j, k)`` in ``in_front``
        (j in front of k: k may be hidden there) and, once a label pool exists (``constrained``:
        the pairs ``(i, j)`` it holds rays of; None before the first), those of every j it holds
        no ray of with k in either order though it holds rays of both j and k with other objects:
        both fields are opaque enough for the pool to see them, so no field bleeds there, and
        carving would keep emptying what k hides behind j, the only place the pair's bound can
        be read. (An object the pool holds no ray of, its field not yet opaque, stays carved.)
        """
        T, H, W = self.T, self.H, self.W
        lab = self.labels.reshape(T, H, W)
        object_band = band if object_band is None else object_band
        out = []
        for k in range(self.K):
            mask = (lab == k).float()[:, None]
            near = F.max_pool2d(mask, 2 * band + 1, stride=1, padding=band)[:, 0] > 0
            free = near & ((lab == -1) | ((lab == self.anchor) & (k != self.anchor)))
            if k != self.anchor and object_band > 0:
                close = F.max_pool2d(mask, 2 * object_band + 1, stride=1, padding=object_band)[:, 0] > 0
                other = (lab >= 0) & (lab != k)
                spared = {j for j, behind in in_front if behind == k}
                if constrained is not None:
                    pooled = {i for pair in constrained for i in pair}  # objects the pool sees opaque
                    if k in pooled:
                        spared |= {j for j in pooled if (j, k) not in constrained and (k, j) not in constrained}
                for j in sorted(spared - {k, self.anchor}):
                    other &= lab != j
                free |= close & other
            keep = free & self.present[k][:, None, None] & ~self.ignored.reshape(T, H, W)
            out.append(torch.nonzero(keep.reshape(-1))[:, 0])
        return out

    def hidden_anchor_strips(self, length: int = 5) -> torch.Tensor:
        """Flat pixel indices ``(S, length)`` of image-row and image-column strips that cross a
        pixel where an object hides the anchor: every pixel of a strip lies in the image and
        shows the anchor or an object (none empty, none ignored), in a frame where the anchor is
        posed. Empty ``(0, length)`` when no object ever hides it. The strips' visible anchor
        pixels anchor the hidden ones to the visible surface around them
        (:func:`osn.train.losses.disparity_curvature`)."""
        T, H, W = self.T, self.H, self.W
        lab = self.labels.reshape(T, H, W)
        shown = (lab >= 0) & ~self.ignored.reshape(T, H, W) & self.present[self.anchor][:, None, None]
        hidden = shown & (lab != self.anchor)
        h = length // 2
        out = []
        for axis, step, n in ((1, W, H), (2, 1, W)):
            # Centres whose whole strip (offsets -h..h along the axis) is shown and crosses a hidden pixel.
            whole, crosses = shown.clone(), torch.zeros_like(hidden)
            for o in range(-h, h + 1):
                whole &= torch.roll(shown, -o, axis)
                crosses |= torch.roll(hidden, -o, axis)
            i = torch.arange(n, device=self.device)
            inside = (i >= h) & (i < n - h)  # torch.roll wraps around; strips may not
            whole &= inside[:, None] if axis == 1 else inside[None, :]
            centre = torch.nonzero((whole & crosses).reshape(-1))[:, 0]
            out.append(centre[:, None] + torch.arange(-h, h + 1, device=self.device)[None, :] * step)
        return torch.cat(out)

    def edge_pairs(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per object its silhouette pixels and, for each, the 4-neighbour on its mask farthest from
        the mask's boundary: two flat ``(E,)`` index tensors (same frame). The image border is no
        silhouette; pixels of one-pixel-wide parts (no neighbour deeper inside) are left out."""
        from scipy.ndimage import distance_transform_edt

        T, H, W = self.T, self.H, self.W
        lab = self.labels.reshape(T, H, W).cpu().numpy()
        ok = ~self.ignored.reshape(T, H, W).cpu().numpy()
        flat = np.arange(T * H * W).reshape(T, H, W)
        # Each pixel's 4 neighbours as (destination, source) slices; off-image ones stay empty.
        shifts = [((slice(None), slice(max(-dy, 0), H - max(dy, 0)), slice(max(-dx, 0), W - max(dx, 0))),
                   (slice(None), slice(max(dy, 0), H - max(-dy, 0)), slice(max(dx, 0), W - max(-dx, 0))))
                  for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        out = []
        for k in range(self.K):
            m = lab == k
            dist = np.stack([distance_transform_edt(m[t]) for t in range(T)])  # 0 off the mask, 1 on its edge
            best = np.zeros_like(dist)  # the deepest neighbour's distance, and its flat index
            arg = np.full(dist.shape, -1, dtype=np.int64)
            for dst, src in shifts:
                nd = np.zeros_like(dist)
                nf = np.full(dist.shape, -1, dtype=np.int64)
                nd[dst], nf[dst] = dist[src], flat[src]
                better = nd > best
                best, arg = np.where(better, nd, best), np.where(better, nf, arg)
            sel = m & ok & (dist == 1.0) & (best > 1.0)
            out.append((torch.from_numpy(flat[sel]).to(self.device), torch.from_numpy(arg[sel]).to(self.device)))
        return out

    @property
    def has_depth(self) -> bool:
        return self.sp_depth.numel() > 0

    def object_rays(self, fields: list[Field], frames: torch.Tensor, sbar: torch.Tensor, objects: list[int] | None = None) -> list[ObjectRays]:
        """Per-object views of rays from training ``frames (R,)`` for configuration ``sbar (K,)``."""
        out = []
        for k in objects if objects is not None else range(self.K):
            s = sbar[k].float()
            P = self.poses[k, frames].clone()
            P[:, :3, :3] = P[:, :3, :3] / s  # cam_to_obj_k @ diag(1/s): scaling about the camera
            out.append(ObjectRays(fields[k], P, self.present[k, frames], self.t_range[k] * s, self.guide if k == self.anchor else 0))
        return out
