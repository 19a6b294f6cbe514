"""Per-object radiance fields (the paper's "object scale-invariant representation").

Every field lives in its object's own coordinates and unit and only inside the object's canonical
box (``ObjectInputs.bbox``); outside the box density is zero. Two implementations share one
interface (:class:`Field`):

* :class:`DenseGridField`: a dense density + RGB voxel grid sampled trilinearly, no MLP. Fast on
  CPU and exact for view-independent appearance (benchgen's emission materials).
* :class:`TensoRFVM`: the paper's TensoRF vector-matrix decomposition (density and appearance
  planes x lines, appearance basis, small colour MLP on features + view direction), with
  TensoRF's coarse-to-fine upsampling.

Both support :meth:`Field.set_resolution` so training can grow them (and a checkpoint can
re-create the right parameter shapes before loading a state dict).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from scenecore.config import Rule, choice, integer, number, validate

#: Added to the raw density before softplus so a zero-initialised field starts nearly empty
#: (TensoRF's ``density_shift``): unobserved space then stays empty instead of becoming floaters.
DENSITY_SHIFT = -4.0

#: Adam rate of the fields' networks (TensoRF's appearance basis and colour MLP; a dense field has
#: none): the paper's 0.001 (appendix "Details of the Joint Optimization", Training Schedule).
NET_LR = 1e-3


def grid_sample_2d(planes: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``planes (P, C, H, W)`` at ``uv (P, N, 2)`` in [-1, 1]; returns ``(P, C, N)``."""
    return F.grid_sample(planes, uv.unsqueeze(2), mode="bilinear", align_corners=True).squeeze(-1)


class Field(nn.Module):
    """Density and colour of one object inside its canonical box.

    Subclasses implement :meth:`_density_raw` and :meth:`_color` on box-normalised points in
    [-1, 1]^3; this class handles the box, the activation and the out-of-box zeroing.
    """

    view_dependent: bool = False

    def __init__(self, bbox: torch.Tensor, resolution: int) -> None:
        super().__init__()
        self.register_buffer("bbox", torch.as_tensor(bbox, dtype=torch.float32).reshape(2, 3).clone())
        self.resolution = int(resolution)

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """Object coordinates ``(N, 3)`` to box coordinates in [-1, 1]^3."""
        lo, hi = self.bbox[0], self.bbox[1]
        return (x - lo) / (hi - lo) * 2.0 - 1.0

    def inside(self, xn: torch.Tensor) -> torch.Tensor:
        """Bool ``(N,)``: box coordinates ``xn (N, 3)`` lie in the box."""
        return (xn.abs() <= 1.0).all(-1)

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """Volume density ``(N,)`` per object unit of length at object-space points ``x (N, 3)``."""
        xn = self.normalise(x)
        sigma = F.softplus(self._density_raw(xn) + DENSITY_SHIFT)
        return torch.where(self.inside(xn), sigma, torch.zeros_like(sigma))

    def color(self, x: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] ``(N, 3)`` at points ``x`` seen along unit directions ``dirs`` (object frame)."""
        return self._color(self.normalise(x), dirs)

    def _density_raw(self, xn: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _color(self, xn: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def set_resolution(self, resolution: int) -> None:
        """Resample the parameters to ``resolution`` voxels per axis (keeps the represented field)."""
        raise NotImplementedError

    #: Adam rate of the field's grids (the dense grid, the anchor's colour planes, TensoRF's planes
    #: and lines), per field kind: every config of a kind held its value.
    grid_lr: float = 0.0

    def param_groups(self, lr_grid: float | None = None, lr_net: float = NET_LR) -> list[dict]:
        """Optimiser parameter groups: grids at ``lr_grid`` (default: the kind's :attr:`grid_lr`),
        networks at ``lr_net`` (as TensoRF)."""
        raise NotImplementedError


def trilinear(grid: torch.Tensor, resolution: int, xn: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of a channels-last grid ``(R^3, C)`` (x fastest, as ``grid_sample``'s
    W axis, ``align_corners=True``) at points ``xn (N, 3)`` in [-1, 1]; returns ``(N, C)``.

    One gather of the 8 corners instead of ``grid_sample``: on CPU ``grid_sample``'s backward
    is several times slower than the single ``index_add`` this gather back-propagates through.
    """
    r = resolution
    p = (xn.clamp(-1.0, 1.0) + 1.0) * (0.5 * (r - 1))
    i0 = p.detach().floor().clamp(0, r - 2)
    f = p - i0
    i0 = i0.long()
    base = (i0[:, 2] * r + i0[:, 1]) * r + i0[:, 0]
    offs = torch.tensor([dz * r * r + dy * r + dx for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], device=xn.device)
    wx = torch.stack([1 - f[:, 0], f[:, 0]], -1)
    wy = torch.stack([1 - f[:, 1], f[:, 1]], -1)
    wz = torch.stack([1 - f[:, 2], f[:, 2]], -1)
    w = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(-1, 8, 1)
    # index_select, not grid[idx]: its backward (index_add) is deterministic on CPU, which
    # exact resume needs; advanced indexing accumulates in a thread-dependent order.
    vals = torch.index_select(grid, 0, (base[:, None] + offs).reshape(-1)).view(-1, 8, grid.shape[1])
    return (vals * w).sum(1)


def trilinear_frozen(grid_cf: torch.Tensor, xn: torch.Tensor) -> torch.Tensor:
    """:func:`trilinear` for a grid no gradient flows to: ``grid_cf (1, C, R, R, R)`` channels first
    (``(R^3, C)``'s transpose, z slowest) at ``xn (N, 3)`` in [-1, 1]; returns ``(N, C)``.

    ``grid_sample``'s forward is one fused kernel: on CPU several times faster than the gather
    for one channel (density, the pass every sample takes). Equal to :func:`trilinear` to float
    rounding (points outside the box are clamped to it by both).
    """
    n = xn.shape[0]
    out = F.grid_sample(grid_cf, xn.view(1, n, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(grid_cf.shape[1], n).T


#: The axes of the three colour planes of :func:`triplane` (xy, xz, yz).
PLANE_AXES = ((0, 1), (0, 2), (1, 2))


def triplane(planes: torch.Tensor, size: int, xn: torch.Tensor) -> torch.Tensor:
    """Sum of bilinear lookups in three axis-aligned planes ``planes (3 * size^2, C)`` (plane i of
    :data:`PLANE_AXES` in rows ``i * size^2 ...``, its first axis fastest, ``align_corners=True``) at
    points ``xn (N, 3)`` in [-1, 1]; returns ``(N, C)``.

    A surface is a 2D set, so three ``size^2`` planes hold texture a ``size^3`` grid would need
    for the same detail (each surface point has its own coordinates in most of the planes).
    One gather of the 12 corners, as :func:`trilinear` (deterministic backward on CPU).
    """
    n = size
    p = (xn[:, [a for ab in PLANE_AXES for a in ab]].view(-1, 3, 2).clamp(-1.0, 1.0) + 1.0) * (0.5 * (n - 1))
    i0 = p.detach().floor().clamp(0, n - 2)
    f = p - i0  # (N, 3, 2)
    i0 = i0.long()
    base = torch.arange(3, device=xn.device) * n * n + i0[..., 1] * n + i0[..., 0]  # (N, 3)
    offs = torch.tensor([0, 1, n, n + 1], device=xn.device)
    fu, fv = f[..., 0], f[..., 1]
    w = torch.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], -1).reshape(-1, 12, 1)
    vals = torch.index_select(planes, 0, (base[..., None] + offs).reshape(-1)).view(-1, 12, planes.shape[1])
    return (vals * w).sum(1)


class DenseGridField(Field):
    """Dense voxel grid: channel 0 raw density, channels 1-3 raw RGB (sigmoid), no MLP.

    Stored channels-last as ``(R^3, 4)`` so one lookup returns density and colour together.
    Without autograd (evaluation, label pools, export) lookups go through
    :func:`trilinear_frozen` on a channels-first copy, made again whenever the grid changes.

    With ``planes > 0`` the raw RGB also adds :func:`triplane` colour planes of ``planes^2`` texels
    (zero at the start, so the field starts as the grid alone; their size does not change with
    :meth:`set_resolution`): texture finer than the grid's voxels on surfaces, for the anchor,
    whose box spans the whole scene (``FieldConfig.anchor_planes``).
    """

    view_dependent = False
    #: The dense grid's rate in every config since the first (no MLP: the grid holds the colour).
    grid_lr = 0.2

    def __init__(self, bbox: torch.Tensor, resolution: int, planes: int = 0) -> None:
        super().__init__(bbox, resolution)
        self.grid = nn.Parameter(torch.zeros(self.resolution**3, 4))
        self.plane_size = int(planes)
        self.planes = nn.Parameter(torch.zeros(3 * self.plane_size**2, 3)) if self.plane_size else None
        self._frozen: tuple[tuple, torch.Tensor] | None = None

    def _raw_rgb(self, raw: torch.Tensor, xn: torch.Tensor) -> torch.Tensor:
        """The grid's raw RGB ``raw (N, 3)`` plus the colour planes' at ``xn (N, 3)``."""
        return raw if self.planes is None else raw + triplane(self.planes, self.plane_size, xn)

    def _lookup(self, channels: slice, xn: torch.Tensor) -> torch.Tensor:
        """Raw grid values ``(N, C)`` of ``channels`` at box coordinates ``xn (N, 3)``."""
        if torch.is_grad_enabled():
            return trilinear(self.grid[:, channels], self.resolution, xn)
        key = (self.grid.data_ptr(), self.grid._version, self.grid.device, self.resolution)
        if self._frozen is None or self._frozen[0] != key:
            r = self.resolution
            self._frozen = (key, self.grid.detach().T.reshape(1, -1, r, r, r).contiguous())
        return trilinear_frozen(self._frozen[1][:, channels], xn)

    def _density_raw(self, xn: torch.Tensor) -> torch.Tensor:
        return self._lookup(slice(0, 1), xn)[:, 0]

    def _color(self, xn: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self._raw_rgb(self._lookup(slice(1, 4), xn), xn))

    def density_and_color(self, x: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``(N,)`` and RGB ``(N, 3)`` at points ``x (N, 3)`` seen along ``dirs (N, 3)``, with a
        single 4-channel lookup (the common case in training)."""
        xn = self.normalise(x)
        v = self._lookup(slice(0, 4), xn)
        sigma = F.softplus(v[:, 0] + DENSITY_SHIFT)
        sigma = torch.where(self.inside(xn), sigma, torch.zeros_like(sigma))
        return sigma, torch.sigmoid(self._raw_rgb(v[:, 1:], xn))

    @torch.no_grad()
    def set_resolution(self, resolution: int) -> None:
        r0, r = self.resolution, int(resolution)
        if r == r0:
            return
        g = self.grid.data.T.reshape(1, 4, r0, r0, r0)
        g = F.interpolate(g, size=(r, r, r), mode="trilinear", align_corners=True)[0]
        self.grid = nn.Parameter(g.reshape(4, -1).T.contiguous())
        self.resolution = r

    def param_groups(self, lr_grid: float | None = None, lr_net: float = NET_LR) -> list[dict]:
        lr = self.grid_lr if lr_grid is None else lr_grid
        return [{"params": [self.grid] + ([self.planes] if self.planes is not None else []), "lr": lr}]


def positional_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """NeRF frequency encoding ``[sin(2^i x), cos(2^i x)]`` for i < freqs (without x itself).

    ``x (..., C)`` -> ``(..., 2 * C * freqs)`` (sines of every channel and frequency, then cosines).
    """
    if freqs == 0:
        return x[..., :0]
    scales = 2.0 ** torch.arange(freqs, device=x.device, dtype=x.dtype)
    xb = (x[..., None] * scales).flatten(-2)
    return torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1)


# Plane (a, b) and line c of the three VM components, as in TensoRF.
_MAT_MODE = ((0, 1), (0, 2), (1, 2))
_VEC_MODE = (2, 1, 0)


class TensoRFVM(Field):
    """TensoRF vector-matrix field: sigma = sum_j 1^T (h_j(plane) * k_j(line)),
    A = B [f_j(plane) * g_j(line)]_j, rgb = MLP(A, PE(A), dir, PE(dir)).

    The component counts default to the paper's (appendix "Details of Networks": 16 density and
    48 appearance components, TensoRF's 27-channel appearance basis, its colour MLP of two hidden
    layers of 128 and its grid rate 0.02)."""

    view_dependent = True
    grid_lr = 0.02

    def __init__(
        self,
        bbox: torch.Tensor,
        resolution: int,
        density_components: int = 16,
        appearance_components: int = 48,
        app_dim: int = 27,
        hidden: int = 128,
        view_freqs: int = 2,
        feat_freqs: int = 2,
        init_scale: float = 0.1,
        seed: int = 0,
    ) -> None:
        super().__init__(bbox, resolution)
        g = torch.Generator().manual_seed(seed)
        r = self.resolution
        self.density_planes = nn.Parameter(init_scale * torch.randn(3, density_components, r, r, generator=g))
        self.density_lines = nn.Parameter(init_scale * torch.randn(3, density_components, r, 1, generator=g))
        self.app_planes = nn.Parameter(init_scale * torch.randn(3, appearance_components, r, r, generator=g))
        self.app_lines = nn.Parameter(init_scale * torch.randn(3, appearance_components, r, 1, generator=g))
        self.basis = nn.Linear(3 * appearance_components, app_dim, bias=False)
        self.view_freqs, self.feat_freqs = view_freqs, feat_freqs
        in_dim = app_dim * (1 + 2 * feat_freqs) + 3 * (1 + 2 * view_freqs)
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 3))
        with torch.no_grad():  # deterministic MLP init from the field's own seed
            for m in list(self.mlp) + [self.basis]:
                if isinstance(m, nn.Linear):
                    bound = 1.0 / m.in_features**0.5
                    m.weight.uniform_(-bound, bound, generator=g)
                    if m.bias is not None:
                        m.bias.zero_()

    @staticmethod
    def _coords(xn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        planes = torch.stack([xn[:, list(m)] for m in _MAT_MODE])  # (3, N, 2)
        lines = torch.stack([xn[:, v] for v in _VEC_MODE])  # (3, N)
        lines = torch.stack([torch.zeros_like(lines), lines], dim=-1)  # (3, N, 2): (x=0, y=line)
        return planes, lines

    def _vm(self, planes: torch.Tensor, lines: torch.Tensor, xn: torch.Tensor) -> torch.Tensor:
        pc, lc = self._coords(xn)
        return grid_sample_2d(planes, pc) * grid_sample_2d(lines, lc)  # (3, C, N)

    def _density_raw(self, xn: torch.Tensor) -> torch.Tensor:
        return self._vm(self.density_planes, self.density_lines, xn).sum(dim=(0, 1))

    def _color(self, xn: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        feat = self._vm(self.app_planes, self.app_lines, xn)  # (3, C, N)
        feat = self.basis(feat.permute(2, 0, 1).reshape(xn.shape[0], -1))
        h = torch.cat([feat, positional_encoding(feat, self.feat_freqs), dirs, positional_encoding(dirs, self.view_freqs)], -1)
        return torch.sigmoid(self.mlp(h))

    def density_and_color(self, x: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``(N,)`` and RGB ``(N, 3)`` at points ``x (N, 3)`` seen along ``dirs (N, 3)``."""
        return self.density(x), self.color(x, dirs)

    @torch.no_grad()
    def set_resolution(self, resolution: int) -> None:
        r = int(resolution)
        if r == self.resolution:
            return
        for name in ("density_planes", "app_planes"):
            p = getattr(self, name).data
            setattr(self, name, nn.Parameter(F.interpolate(p, size=(r, r), mode="bilinear", align_corners=True).contiguous()))
        for name in ("density_lines", "app_lines"):
            p = getattr(self, name).data
            setattr(self, name, nn.Parameter(F.interpolate(p, size=(r, 1), mode="bilinear", align_corners=True).contiguous()))
        self.resolution = r

    def param_groups(self, lr_grid: float | None = None, lr_net: float = NET_LR) -> list[dict]:
        grids = [self.density_planes, self.density_lines, self.app_planes, self.app_lines]
        lr = self.grid_lr if lr_grid is None else lr_grid
        return [{"params": grids, "lr": lr}, {"params": list(self.basis.parameters()) + list(self.mlp.parameters()), "lr": lr_net}]


#: ``field`` options added after runs were first written, with the value that trained those runs
#: (``TrainConfig.from_yaml(..., run_config=True)`` fills them in; ``load_run`` reads each field's
#: size and planes from the checkpoint itself).
FIELD_ADDED_LATER: dict[str, Any] = {"object_resolution": 0, "anchor_planes": 0}
#: ``field`` options that are gone, with the value that trains as today (the term off): a run's
#: config at that value reads without them (``TrainConfig.from_yaml(..., run_config=True)``), and
#: ``load_run`` ignores them (TensoRF's sizes are its constructor's defaults now: a checkpoint of
#: other sizes does not load).
FIELD_REMOVED_OPTIONS: dict[str, Any] = {"tv_density": 0.0, "density_components": 16, "appearance_components": 48,
                                         "app_dim": 27, "lr_net": 1e-3,
                                         # a function of the field mapping: the kind's value today
                                         "hidden": lambda f: 128 if f.get("kind") == "tensorf" else f.get("hidden"),
                                         "lr_grid": lambda f: 0.02 if f.get("kind") == "tensorf" else 0.2}


#: Most voxels per axis of a grid (the paper's largest is 640) and texels per side of a plane:
#: above, a typo would allocate many GB before the first step.
MAX_RESOLUTION = 1024
MAX_PLANE_SIZE = 8192

_FIELD_RULES: dict[str, Rule] = {
    "kind": choice("dense", "tensorf"),
    # Trilinear interpolation needs 2 voxels per axis.
    "resolution": integer(2, MAX_RESOLUTION),
    "initial_resolution": integer(2, MAX_RESOLUTION),
    "upsample_steps": integer(0, 64),
    "object_resolution": Rule(lambda v: v == "auto" or integer(0, MAX_RESOLUTION).ok(v), f"auto or an integer in 0..{MAX_RESOLUTION}"),
    # Bilinear interpolation needs 2 texels per side; 0 = no planes.
    "anchor_planes": Rule(lambda v: v == "auto" or (integer(0, MAX_PLANE_SIZE).ok(v) and v != 1),
                          f"auto, 0 or an integer in 2..{MAX_PLANE_SIZE}"),
}


@dataclass
class FieldConfig:
    """Which field and how big (the ``field`` mapping of a training config).

    Each option's docstring begins with its category (``paper (...)``, ``addition (...)`` or
    ``infrastructure``) and names its neutral value; docs/training.md's Options table is generated
    from them (``scripts/docs_generate.py``).
    """

    kind: str = "dense"
    """addition (experiments/2026-11-24-measurements-two-cores.md): ``dense``
    (:class:`DenseGridField`: a density and RGB voxel grid, no MLP; faster per iteration on a CPU)
    or ``tensorf`` (:class:`TensoRFVM`, the paper's field). Unit: a choice. Neutral: ``tensorf``
    (the paper's field)."""
    resolution: int = 64
    """paper (appendix "Details of Networks", Object Scale-Invariant Representation Module):
    Final voxels per axis of the anchor's field, and the most any object's field reaches. Unit:
    voxels per axis. Neutral: none."""
    initial_resolution: int = 32
    """paper (appendix "Details of Networks", Object Scale-Invariant Representation Module:
    coarse-to-fine, as TensoRF): Voxels per axis the fields start at. Unit: voxels per axis.
    Neutral: the value of ``resolution`` (no upsampling)."""
    upsample_steps: int = 2
    """paper (appendix "Details of Networks", Object Scale-Invariant Representation Module:
    coarse-to-fine, as TensoRF): Log-spaced resolution increases from ``initial_resolution`` to
    the final resolution over the first 40% of all field iterations. Unit: steps. Neutral: 0 (the
    fields start at their final resolution)."""
    object_resolution: int | str = "auto"
    """addition (experiments/2026-11-27-object-resolution-anchor-planes.md): Final voxels per axis
    of every object's field but the anchor's (at most ``resolution``), grown on the anchor's
    schedule scaled to it. ``auto`` (:func:`osn.train.auto.object_resolutions`): on noisy inputs
    (:mod:`osn.preprocess.depth_noise`; SfM's) as many as the object's box spans pixels in its
    training frames (:func:`osn.train.auto.footprint_resolution`), ``resolution`` on exact ones.
    Unit: voxels per axis. Neutral: 0 (``resolution``)."""
    anchor_planes: int | str = "auto"
    """addition (experiments/2026-11-27-object-resolution-anchor-planes.md,
    experiments/2026-11-28-one-rule-room-options.md): Texels per side of three colour planes added
    to the anchor's RGB (:func:`triplane`; ``dense`` only, TensoRF's own planes hold its colour).
    ``auto`` (:func:`osn.train.auto.anchor_plane_size`): about one texel per pixel where the
    anchor's box spans more pixels than its grid has voxels, else none. Unit: texels per side.
    Neutral: 0 (the grid's colour alone)."""

    def __post_init__(self) -> None:
        validate(self, "field", _FIELD_RULES)

    def resolutions(self, final: int | None = None) -> list[int]:
        """The resolution after each upsampling step, from ``initial_resolution`` to ``resolution``;
        with ``final``, the same steps scaled to end at ``final`` (at least 2 voxels each)."""
        if self.upsample_steps <= 0 or self.initial_resolution >= self.resolution:
            steps = [self.resolution]
        else:
            n = self.upsample_steps
            lo, hi = float(self.initial_resolution), float(self.resolution)
            steps = [int(round(lo * (hi / lo) ** (i / n))) for i in range(n + 1)]
        if final is None or final == self.resolution:
            return steps
        return [max(2, int(round(r * final / self.resolution))) for r in steps]


def saved_plane_size(state: dict[str, Any]) -> int:
    """Texels per side of the colour planes a field's ``state_dict`` holds (0: none), so a
    checkpoint's field is rebuilt as it trained, whatever ``anchor_planes: auto`` would give now."""
    return int(round((state["planes"].shape[0] / 3) ** 0.5)) if "planes" in state else 0


def make_field(cfg: FieldConfig, bbox: torch.Tensor, seed: int = 0, resolution: int | None = None,
               planes: int = 0) -> Field:
    """Build the configured field for one object's box ``bbox (2, 3)`` (at ``resolution`` or the
    initial one); a dense field with ``planes`` texels per side of colour planes (the anchor's)."""
    r = resolution if resolution is not None else cfg.resolutions()[0]
    if cfg.kind == "dense":
        return DenseGridField(bbox, r, planes)
    if cfg.kind == "tensorf":
        return TensoRFVM(bbox, r, seed=seed)
    raise ValueError(f"unknown field kind {cfg.kind!r} (expected 'dense' or 'tensorf')")
