"""Physical plausibility of a scale configuration (numpy + trimesh, no rendering).

A configuration is plausible when, at every timestamp,

1. every object stays inside the room. The room is a convex box containing every training camera
   centre ``c_t``, and object k's vertices move to ``c_t + s_k (p - c_t)``; so each vertex gives an
   upper bound on ``s_k`` and, by convexity, checking the mesh vertices is exact for the whole
   mesh. ``room_scale_limits`` returns these bounds; shrinking (towards the camera) never leaves
   the room.
2. no two objects interpenetrate: each object's probe points (vertices + seeded surface samples)
   are mapped into the other's frame and tested against its analytic primitives (or, for mesh
   files, trimesh's watertight containment); both directions. Bounding spheres skip far pairs.
   This is exact up to the probe density (a sliver thinner than the sample spacing can be missed).
3. no camera centre (training or test) lies inside an object.
"""

from __future__ import annotations

import numpy as np

from scenecore.cameras import invert_pose
from benchgen.scene.geometry import BuiltScene
from benchgen.scene.spec import SpecError

#: Slack in metres for "inside the room": objects resting on the floor at scale 1 stay valid.
ROOM_TOLERANCE = 1e-6


def _outside_room(built: BuiltScene, point: np.ndarray) -> bool:
    """Whether ``point`` (world) is not strictly inside the room box, up to ``ROOM_TOLERANCE``."""
    lo, hi = built.room_box
    return bool(np.any(point <= lo - ROOM_TOLERANCE) or np.any(point >= hi + ROOM_TOLERANCE))


def room_scale_limits(built: BuiltScene) -> np.ndarray:
    """``(K,)`` largest scale of each object that keeps all its vertices in the room at every t.

    The anchor's limit is 1. Raises ``SpecError`` if a training camera is outside the room.
    """
    lo, hi = built.room_box
    lo, hi = lo - ROOM_TOLERANCE, hi + ROOM_TOLERANCE
    centers = built.scene.training_camera_centers()
    for t, c in enumerate(centers):
        if _outside_room(built, c):
            raise SpecError(f"{built.spec.source}: rig: the training camera at time index {t} is outside the room")
    limits = np.ones(len(built.objects))
    for k in range(1, len(built.objects)):
        verts = built.objects[k].mesh.vertices
        best = np.inf
        for t, c in enumerate(centers):
            pose = built.scene.objects[k].poses[t]
            q = verts @ pose[:3, :3].T + pose[:3, 3] - c
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(q > 0, (hi - c) / q, np.where(q < 0, (lo - c) / q, np.inf))
            best = min(best, float(s.min()))
        limits[k] = best
    return limits


class PlausibilityChecker:
    """Checks conditions 2 and 3 of the module docstring for scale vectors of one scene."""

    def __init__(self, built: BuiltScene):
        self.built = built
        self.K = len(built.objects)
        self.camera_centers = [(f.name, f.time_index, f.camera_to_world[:3, 3]) for f in built.scene.frames]

    def _overlap(self, a: int, b: int, Ma: np.ndarray, Mb: np.ndarray) -> bool:
        ga, gb = self.built.objects[a], self.built.objects[b]
        (ca, ra), (cb, rb) = ga.bounding_sphere, gb.bounding_sphere
        sa, sb = np.cbrt(np.linalg.det(Ma[:3, :3])), np.cbrt(np.linalg.det(Mb[:3, :3]))
        if np.linalg.norm((Ma[:3, :3] @ ca + Ma[:3, 3]) - (Mb[:3, :3] @ cb + Mb[:3, 3])) > sa * ra + sb * rb:
            return False
        for (g_from, M_from), (g_to, M_to) in (((ga, Ma), (gb, Mb)), ((gb, Mb), (ga, Ma))):
            rel = invert_pose(M_to) @ M_from
            if g_to.contains(g_from.probe_points @ rel[:3, :3].T + rel[:3, 3]).any():
                return True
        return False

    def problem(self, scales: np.ndarray) -> str | None:
        """``None`` if plausible, else a short reason naming the objects and the timestamp."""
        names = [g.name for g in self.built.objects]
        for t in range(len(self.built.scene.timestamps)):
            M = self.built.poses(t, scales)
            for a in range(1, self.K):
                for b in range(a + 1, self.K):
                    if self._overlap(a, b, M[a], M[b]):
                        return f"objects {names[a]!r} and {names[b]!r} intersect at time index {t}"
        for name, t, c in self.camera_centers:
            M = self.built.poses(t, scales)
            for k in range(1, self.K):
                rel = invert_pose(M[k])
                if self.built.objects[k].contains((rel[:3, :3] @ c + rel[:3, 3])[None])[0]:
                    return f"the camera of frame {name} is inside object {names[k]!r}"
        return None


def check_authored_scene(built: BuiltScene) -> None:
    """Reject a spec whose own scene (all scales 1) is implausible, before any rendering.

    Test cameras must be inside the room too: one outside sees only the room's outer faces, the
    same in every configuration, and would make the novel views meaningless.
    """
    limits = room_scale_limits(built)
    src = built.spec.source
    for f in built.scene.test_frames:
        if _outside_room(built, f.camera_to_world[:3, 3]):
            raise SpecError(f"{src}: rig: the test camera of frame {f.name} is outside the room")
    for k in range(1, len(built.objects)):
        if limits[k] < 1.0:
            raise SpecError(f"{src}: objects: {built.objects[k].name!r} pokes out of the room during its motion")
    reason = PlausibilityChecker(built).problem(np.ones(len(built.objects)))
    if reason:
        raise SpecError(f"{src}: the authored scene is implausible: {reason}")
