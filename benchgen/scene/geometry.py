"""Scene geometry from a spec: meshes, analytic solid tests, motion and the camera rig (no bpy).

``build_scene`` turns a ``SceneSpec`` into a ``BuiltScene``: one triangle mesh per object in its
own frame (object 0 is the room, the anchor), the per-timestamp object poses, and the dataset
manifest (``scenecore.dataset.Scene``) with cameras from ``scenecore.cameras``. The renderer draws
these meshes; the plausibility checks test points against the same solids.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from scenecore.cameras import intrinsics_from_fov, look_at
from scenecore.dataset import Frame, Intrinsics, Scene, SceneObject
from benchgen.scene.spec import Keyframe, ObjectSpec, Part, RigSpec, SceneSpec, Texture

#: Points sampled on each object's surface for the penetration test (plus its vertices).
SURFACE_SAMPLES = 3000
#: Segments around the axis of cylinders and cones.
REVOLVE_SECTIONS = 48
#: Longest facet side along a revolved profile, in units of the spacing between sections. Thin
#: facets cost exactness (see ``revolved_mesh``), many facets cost time: Cycles re-syncs every
#: moved mesh on each render, and facets of aspect 1 make a gnome-house frame several times slower.
MAX_FACET_ASPECT = 4.0


def euler_matrix(location: list[float], rotation_deg: list[float]) -> np.ndarray:
    """4x4 rigid transform; rotation is Blender's XYZ Euler order (R = Rz Ry Rx), in degrees."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rotation_deg, degrees=True).as_matrix()
    T[:3, 3] = location
    return T


def part_mesh(part: Part) -> trimesh.Trimesh:
    """Triangle mesh of a primitive in its object's frame (cylinder/cone/torus axis = part z)."""
    p = part.params
    if part.type == "box":
        m = trimesh.creation.box(extents=p["size"])
    elif part.type == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=p["radius"])
    elif part.type == "cylinder":
        r, h = p["radius"], p["height"]
        m = revolved_mesh([[0, -h / 2], [r, -h / 2], [r, h / 2], [0, h / 2]])
    elif part.type == "cone":
        r, h = p["radius"], p["height"]
        m = revolved_mesh([[0, -h / 2], [r, -h / 2], [0, h / 2]])  # centred like the cylinder
    elif part.type == "torus":
        m = trimesh.creation.torus(major_radius=p["major_radius"], minor_radius=p["minor_radius"], major_sections=48, minor_sections=24)
    elif part.type == "lathe":
        m = revolved_mesh(lathe_outline(p["profile"]))
    else:  # spec.py rejects unknown types; this guards programmatic use
        raise ValueError(f"unknown part type {part.type!r}")
    m.apply_transform(euler_matrix(part.location, part.rotation))
    return m


def revolved_mesh(profile: list[list[float]], sections: int = REVOLVE_SECTIONS) -> trimesh.Trimesh:
    """Closed surface of revolution about z of a ``(radius, z)`` profile, without long thin facets.

    Each profile segment is split into pieces no longer than ``MAX_FACET_ASPECT`` times the
    spacing between sections at the largest radius. Why: Cycles stores non-instanced meshes in world space, so a rescaled object's
    vertices are rounded anew; a long thin facet (trimesh's cylinder side: 0.5 m x 4 mm for a thin
    pole) turns that rounding into a tilt of its plane and hit points up to 2e-5 m off along the
    facet, which the texture turns into colour differences above the invariance tolerance.
    """
    prof = np.asarray(profile, dtype=np.float64)
    step = MAX_FACET_ASPECT * 2 * np.pi * prof[:, 0].max() / sections
    pts = [prof[0]]
    for a, b in zip(prof[:-1], prof[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        pts.extend(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    return trimesh.creation.revolve(np.array(pts), sections=sections)


def lathe_outline(profile: list[list[float]]) -> list[list[float]]:
    """The polyline ``revolved_mesh`` turns into a lathe's closed surface: the profile polygon
    closed, or, when one of its edges lies on the axis, opened there (that edge sweeps no area)."""
    n = len(profile)
    for i in range(n):
        if profile[i][0] == 0 and profile[(i + 1) % n][0] == 0:
            return [profile[(i + 1 + j) % n] for j in range(n)]  # starts and ends on the axis
    return [*profile, profile[0]]


def inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Whether 2D ``points (N, 2)`` lie inside the simple ``polygon (M, 2)`` (even-odd rule; a
    point on an edge may fall either way)."""
    x, y = points[:, 0:1], points[:, 1:2]
    a, b = polygon, np.roll(polygon, -1, axis=0)
    straddles = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross_x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.count_nonzero(straddles & (x < cross_x), axis=1) % 2).astype(bool)


def part_contains(part: Part, points: np.ndarray) -> np.ndarray:
    """Whether object-frame points lie strictly inside the analytic primitive.

    The analytic solid contains its tessellation, so the test is conservative (it may report a
    point in a facet's gap as inside, never the reverse).
    """
    local = (points - part.location) @ Rotation.from_euler("xyz", part.rotation, degrees=True).as_matrix()
    x, y, z = local.T
    p = part.params
    if part.type == "box":
        return np.all(np.abs(local) < np.asarray(p["size"]) / 2, axis=1)
    if part.type == "sphere":
        return np.einsum("ij,ij->i", local, local) < p["radius"] ** 2
    r = np.hypot(x, y)
    if part.type == "cylinder":
        return (r < p["radius"]) & (np.abs(z) < p["height"] / 2)
    if part.type == "cone":
        h = p["height"]
        return (np.abs(z) < h / 2) & (r < p["radius"] * (0.5 - z / h))
    if part.type == "torus":
        return (r - p["major_radius"]) ** 2 + z**2 < p["minor_radius"] ** 2
    if part.type == "lathe":
        return inside_polygon(np.stack([r, z], axis=1), np.asarray(p["profile"], dtype=np.float64))
    raise ValueError(f"unknown part type {part.type!r}")


@dataclass
class ObjectGeometry:
    """A rigid object's solid in its own frame: render mesh, inside test, probe points."""

    name: str
    mesh: trimesh.Trimesh
    parts: list[Part]
    textures: list[Texture]
    seed: int
    #: Index into ``textures`` per triangle (None: all use ``textures[0]``).
    face_texture: np.ndarray | None = None

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether object-frame points ``(N, 3)`` are strictly inside the solid."""
        if self.parts:
            inside = np.zeros(len(points), dtype=bool)
            for part in self.parts:
                inside |= part_contains(part, points)
            return inside
        solid = self.mesh if self.mesh.is_watertight else self.mesh.convex_hull
        return solid.contains(points)

    @cached_property
    def probe_points(self) -> np.ndarray:
        """Vertices plus seeded surface samples: the points tested against other solids."""
        samples, _ = trimesh.sample.sample_surface(self.mesh, SURFACE_SAMPLES, seed=self.seed)
        return np.concatenate([self.mesh.vertices, samples])

    @cached_property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        c = self.mesh.bounds.mean(axis=0)
        return c, float(np.linalg.norm(self.mesh.vertices - c, axis=1).max())


def object_geometry(o: ObjectSpec, seed: int) -> ObjectGeometry:
    if o.parts:
        mesh = trimesh.util.concatenate([part_mesh(p) for p in o.parts])
    else:
        try:
            loaded = trimesh.load(o.mesh, force="mesh")
        except Exception as e:  # trimesh raises many types for unknown or broken files
            raise ValueError(f"{o.mesh}: cannot load the mesh ({type(e).__name__}: {e})") from None
        if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
            raise ValueError(f"{o.mesh}: trimesh found no triangles")
        mesh = loaded.copy()
        mesh.apply_scale(o.mesh_scale)
    return ObjectGeometry(o.name, mesh, list(o.parts), [o.texture], seed)


def room_geometry(spec: SceneSpec) -> ObjectGeometry:
    """The room: a closed box with inward-facing triangles, floor at z = 0."""
    sx, sy, sz = spec.room.size
    mesh = trimesh.creation.box(extents=[sx, sy, sz])
    mesh.apply_translation([0, 0, sz / 2])
    mesh.invert()
    floor = np.all(np.abs(mesh.vertices[mesh.faces][:, :, 2]) < 1e-9, axis=1)
    return ObjectGeometry("room", mesh, [], [spec.room.floor, spec.room.walls], spec.seed, np.where(floor, 0, 1))


def interpolate_poses(keys: list[Keyframe], times: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` poses at ``times``: linear translation, slerp rotation, clamped at the ends."""
    kt = np.array([k.t for k in keys])
    locs = np.array([k.location for k in keys])
    t = np.clip(times, kt[0], kt[-1])
    out = np.tile(np.eye(4), (len(times), 1, 1))
    out[:, :3, 3] = np.stack([np.interp(t, kt, locs[:, i]) for i in range(3)], axis=1)
    rots = Rotation.from_euler("xyz", [k.rotation for k in keys], degrees=True)
    out[:, :3, :3] = (Slerp(kt, rots)(t) if len(keys) > 1 else Rotation.concatenate([rots] * len(t))).as_matrix()
    return out


def _orbit_eye(rig: RigSpec, angle_deg: float) -> np.ndarray:
    """Camera centre on the rig's arc at ``angle_deg`` (0 = -y of the target), at ``rig.height``."""
    a = np.radians(angle_deg)
    eye = np.asarray(rig.target, dtype=np.float64) + rig.radius * np.array([np.sin(a), -np.cos(a), 0.0])
    eye[2] = rig.height
    return eye


def rig_cameras(rig: RigSpec, t: int) -> np.ndarray:
    """``(views, 4, 4)`` OpenCV camera-to-world poses of every camera of the rig at timestamp ``t``."""
    target = np.asarray(rig.target, dtype=np.float64)
    if rig.protocol == "stereo":
        frac = t / (rig.times - 1) if rig.times > 1 else 0.0
        left = look_at(_orbit_eye(rig, rig.arc[0] + frac * (rig.arc[1] - rig.arc[0])), target)
        right = left.copy()
        right[:3, 3] += rig.baseline * left[:3, 0]  # parallel pair: shifted along the image x axis
        return np.stack([left, right])
    if rig.protocol == "multi-camera":
        centre = look_at(_orbit_eye(rig, float(np.mean(rig.arc))), target)
        rows, cols = rig.grid
        eyes = [centre[:3, 3] + rig.spacing * ((c - (cols - 1) / 2) * centre[:3, 0] + (r - (rows - 1) / 2) * centre[:3, 1])
                for r in range(rows) for c in range(cols)]
        return np.stack([look_at(e, target) for e in eyes])
    angles = np.linspace(*rig.arc, rig.views) if rig.views > 1 else np.array([np.mean(rig.arc)])
    return np.stack([look_at(_orbit_eye(rig, a), target) for a in angles])


def rig_frames(spec: SceneSpec, times: np.ndarray) -> list[Frame]:
    """The training frame at each t (``rig.train_view(t)``) and the rig's test views."""
    rig = spec.rig
    frames = []
    for t in range(len(times)):
        train_v = rig.train_view(t)
        for v, pose in enumerate(rig_cameras(rig, t)):
            if v == train_v or rig.is_test(v, t):
                frames.append(Frame(f"v{v:02d}_t{t:02d}", v, t, "train" if v == train_v else "test", pose))
    test = [i for i, f in enumerate(frames) if f.split == "test"]
    if 0 < rig.test_views < len(test):
        keep = {test[i] for i in np.linspace(0, len(test) - 1, rig.test_views).round().astype(int)}
        frames = [f for i, f in enumerate(frames) if f.split == "train" or i in keep]
    return frames


@dataclass
class BuiltScene:
    """A spec made concrete: geometry per object (0 = room) and the dataset manifest."""

    spec: SceneSpec
    objects: list[ObjectGeometry]
    scene: Scene

    @property
    def room_box(self) -> tuple[np.ndarray, np.ndarray]:
        sx, sy, sz = self.spec.room.size
        return np.array([-sx / 2, -sy / 2, 0.0]), np.array([sx / 2, sy / 2, sz])

    def poses(self, time_index: int, scales: np.ndarray | None = None) -> np.ndarray:
        """``(K, 4, 4)`` object-to-world poses at a timestamp, optionally in a configuration."""
        if scales is None:
            return np.stack([o.poses[time_index] for o in self.scene.objects])
        return np.stack([self.scene.configured_pose(k, time_index, float(s)) for k, s in enumerate(scales)])


def build_scene(spec: SceneSpec, num_configurations: int | None = None) -> BuiltScene:
    """Build geometry, motion and cameras. Raises ``ValueError`` for unreadable meshes."""
    T = spec.rig.times
    times = np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1)
    geoms = [room_geometry(spec)] + [object_geometry(o, spec.seed + 1 + i) for i, o in enumerate(spec.objects)]
    objects = [SceneObject(0, "room", "anchor", np.tile(np.eye(4), (T, 1, 1)))]
    objects += [SceneObject(i + 1, o.name, "object", interpolate_poses(o.keyframes, times)) for i, o in enumerate(spec.objects)]
    K = intrinsics_from_fov(spec.rig.fov, spec.width, spec.height)
    scene = Scene(
        width=spec.width,
        height=spec.height,
        intrinsics=Intrinsics.from_matrix(K),
        timestamps=times,
        num_views=spec.rig.views,
        frames=rig_frames(spec, times),
        objects=objects,
        num_configurations=spec.configs if num_configurations is None else num_configurations,
        generator={"tool": "benchgen", "spec": spec.name, "seed": spec.seed, "samples": spec.samples, "margin": spec.margin},
    )
    return BuiltScene(spec, geoms, scene)
