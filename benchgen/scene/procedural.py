"""A procedural scene family: a valid, plausible scene spec from an integer seed (numpy + trimesh).

``random_spec(seed)`` draws a room with random textures, 2 to 6 movers, each one of a vocabulary
of shapes made of primitive and lathe parts (thin plates and rods, rings and arches with holes,
cups, tables and L-shapes that are concave), sized over a decade (0.15 m to 1.5 m), textured and
keyframed, and the camera rig of one of the three protocols with a random arc, height, distance
and field of view. About half the movers stand on the floor and turn about the vertical only (their
base touches the floor at every time: the contact case), the others fly and tumble; about half the
movers after the first are sent across the line of sight of an earlier one, in front of or behind
it (the occlusion case).

The number of movers is drawn from the seed alone; the rest of a draw is kept when it passes the checks any spec passes (``plausibility.check_authored_scene``:
inside the room, no interpenetration, no camera inside an object) and the family's own: every
mover in view (centre inside the image, in front of the camera, at least ``MIN_EXTENT`` of the
image width across) in at least ``MIN_VISIBLE_SHARE`` of the training frames; some mover on the
floor; some pair whose image discs overlap in a training frame. A rejected draw is redrawn
(with the same number of movers) from the next sub-seed, so a seed always gives the same spec (``Generator([seed, attempt])``).

The draw is independent of resolution and G: ``resolution`` and ``configs`` only set the spec's
render settings, so ``--random 7 --resolution 128`` is seed 7's scene at 128 px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchgen.scene.geometry import build_scene, interpolate_poses, rig_cameras
from benchgen.scene.plausibility import check_authored_scene
from benchgen.scene.shapes import SHAPES, normalised, part_dict_mesh, texture
from benchgen.scene.shapes import uniform as _u
from benchgen.scene.spec import RIG_PROTOCOLS, Keyframe, RigSpec, SceneSpec, SpecError, spec_from_dict
from scenecore.cameras import intrinsics_from_fov, project

#: The two fixed splits of the family: tune defaults on ``development``, report on ``held-out``
#: and never tune on it. Seeds are half-open ranges; docs/benchgen.md states them too.
SPLITS: dict[str, range] = {"development": range(0, 1000), "held-out": range(1000, 2000)}
#: Movers per scene (inclusive).
MOVERS = (2, 6)
#: Largest extent of a mover in metres: log-uniform over a decade.
SIZE_RANGE = (0.15, 1.5)
#: A mover counts as in view in a training frame when its centre projects inside the image, in
#: front of the camera, and its projected extent is at least this share of the image width (8 px
#: at 64 px); it must be in view in at least ``MIN_VISIBLE_SHARE`` of the training frames.
MIN_EXTENT = 1.0 / 8
MIN_VISIBLE_SHARE = 0.6
#: And its surface covers at least this many pixels of the family's 64 x 64 grid in as many
#: frames, where no other mover is in front of it (:func:`visible_pixels`): twice the 16 pixels
#: below which ``osn oracle`` refuses an object in every frame. Without occlusion a mover standing
#: behind a table passed while showing a few pixels, and no method could be trained on it.
MIN_PIXELS = 32
#: The grid the pixel count uses, whatever the dataset's resolution (a seed's scene must not
#: depend on it).
GRID = 64
#: Draws tried before a seed is reported as unusable (none has needed more than a few dozen).
MAX_ATTEMPTS = 500
#: Draws of one mover before the scene is drawn anew with it where it collides.
MOVER_TRIES = 30
#: Render settings of the family's datasets (the demo's size: 64 px, 30 test views, G = 20).
DEFAULTS = {"resolution": 64, "configs": 20, "test_views": 30}


@dataclass
class Mover:
    """One drawn object before it becomes a spec entry: parts in its frame (base at z = 0),
    largest extent, and whether it stands on the floor."""

    name: str
    parts: list[dict[str, Any]]
    size: float
    on_floor: bool


def split_of(seed: int) -> str:
    """The split a seed belongs to (``development``, ``held-out`` or ``unassigned``)."""
    return next((name for name, seeds in SPLITS.items() if seed in seeds), "unassigned")


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``A:B`` (A to B-1), ``A`` or a comma-separated list of those; ``ValueError`` names the problem."""
    seeds: list[int] = []
    for item in text.split(","):
        item = item.strip()
        try:
            if ":" in item:
                a, b = (int(x) for x in item.split(":"))
                if b <= a:
                    raise ValueError
                seeds.extend(range(a, b))
            else:
                seeds.append(int(item))
        except ValueError:
            raise ValueError(f"bad seed range {item!r} (expected A:B with A < B, or an integer)") from None
    if any(s < 0 for s in seeds):
        raise ValueError(f"seeds must be >= 0, got {text!r}")
    return seeds


# ------------------------------------------------------------------------------------------------
# The draw.
# ------------------------------------------------------------------------------------------------


def _rig(rng: np.random.Generator, protocol: str) -> dict:
    centre, span = _u(rng, -25, 25), _u(rng, 40, 90)
    rig: dict[str, Any] = {
        "protocol": protocol, "times": 15, "fov": round(_u(rng, 50, 70), 2), "radius": round(_u(rng, 2.0, 3.0), 3),
        "height": round(_u(rng, 0.8, 1.8), 3), "arc": [round(centre - span / 2, 2), round(centre + span / 2, 2)],
        "target": [round(_u(rng, -0.4, 0.4), 3), round(_u(rng, 0.2, 0.9), 3), round(_u(rng, 0.3, 0.7), 3)],
    }
    if protocol == "orbit":
        rig.update(views=15, test_views=DEFAULTS["test_views"])
    elif protocol == "stereo":
        span = _u(rng, 10, 30)  # the pair moves slowly, as in Oxford Multimotion
        rig.update(arc=[round(centre - span / 2, 2), round(centre + span / 2, 2)], baseline=round(_u(rng, 0.1, 0.3), 3), views=2)
    else:
        rig.update(arc=[round(centre, 2), round(centre, 2)], grid=[2, 6], views=12, spacing=round(_u(rng, 0.15, 0.3), 3))
    return rig


def _mid_camera(rig: dict) -> tuple[np.ndarray, np.ndarray]:
    """Eye and unit viewing direction of the camera at the middle of the arc."""
    a = math.radians((rig["arc"][0] + rig["arc"][1]) / 2)
    target = np.asarray(rig["target"], dtype=np.float64)
    eye = target + rig["radius"] * np.array([math.sin(a), -math.cos(a), 0.0])
    eye[2] = rig["height"]
    return eye, (target - eye) / np.linalg.norm(target - eye)


def _view_point(rng: np.random.Generator, eye: np.ndarray, forward: np.ndarray, fov: float, depth: float) -> np.ndarray:
    """A world point at ``depth`` along a ray through the central part of the mid camera's image."""
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = math.tan(math.radians(fov) / 2)
    x, y = _u(rng, -0.6, 0.6) * half, _u(rng, -0.5, 0.5) * half
    ray = forward + x * right + y * up
    return eye + depth * ray / np.linalg.norm(ray)


def _motion(rng: np.random.Generator, start: np.ndarray, end: np.ndarray, on_floor: bool) -> list[dict]:
    if on_floor:
        r0 = _u(rng, -180, 180)
        rots = [[0, 0, r0], [0, 0, r0 + _u(rng, -120, 120)]]
    else:
        r0 = rng.uniform(-180, 180, 3)
        rots = [list(r0), list(r0 + rng.uniform(-90, 90, 3))]
    keys = [{"t": 0.0, "location": start, "rotation": rots[0]}, {"t": 1.0, "location": end, "rotation": rots[1]}]
    if rng.random() < 0.5:  # a bend in the path
        mid = (start + end) / 2 + rng.uniform(-0.15, 0.15, 3) * np.array([1, 1, 0 if on_floor else 1])
        keys.insert(1, {"t": round(_u(rng, 0.3, 0.7), 3), "location": mid, "rotation": list((np.asarray(rots[0]) + rots[1]) / 2)})
    return [{"t": k["t"], "location": [round(float(x), 4) for x in k["location"]],
             "rotation": [round(float(x), 2) for x in k["rotation"]]} for k in keys]


def _mesh(parts: list[dict]):
    """The tessellated parts as one mesh (the object's render mesh, as ``geometry`` builds it)."""
    import trimesh

    return trimesh.util.concatenate([part_dict_mesh(p) for p in parts])


def _sphere(verts: np.ndarray) -> tuple[np.ndarray, float]:
    """Bounding sphere (centre in the object frame, radius) of object-frame vertices."""
    c = (verts.min(axis=0) + verts.max(axis=0)) / 2
    return c, float(np.linalg.norm(verts - c, axis=1).max())


def _centres(motion: list[dict], centre: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``(T, 3)`` world positions of an object-frame point under keyframed ``motion``."""
    poses = interpolate_poses([Keyframe(k["t"], k["location"], k["rotation"]) for k in motion], times)
    return poses[:, :3, :3] @ centre + poses[:, :3, 3]


def _mover(rng: np.random.Generator, i: int, on_floor: bool, rig: dict, mids: list[np.ndarray]) -> tuple[dict, np.ndarray]:
    """One mover (spec dict) and its mid-path centre: a shape, a size, a path in view (sometimes
    across the line of sight of an earlier mover at ``mids``) and a texture."""
    eye, forward = _mid_camera(rig)
    shape = str(rng.choice(list(SHAPES)))
    size = float(math.exp(_u(rng, math.log(SIZE_RANGE[0]), math.log(SIZE_RANGE[1]))))
    parts = normalised(SHAPES[shape](rng), size)
    depth = _u(rng, max(0.8, 1.5 * size + 0.5), max(1.0, min(4.0, 5.5 * size + 0.6)))
    if mids and rng.random() < 0.5:  # across the line of sight of an earlier mover, in front or behind
        other = mids[int(rng.integers(len(mids)))]
        mid = eye + (other - eye) * (_u(rng, 0.55, 0.75) if rng.random() < 0.5 else _u(rng, 1.3, 1.6))
    else:
        mid = _view_point(rng, eye, forward, rig["fov"], depth)
    side = np.cross(mid - eye, [0.0, 0.0, 1.0])
    side /= max(np.linalg.norm(side), 1e-9)
    travel = side * _u(rng, 0.3, 1.0) * max(size, 0.5) * (1 if rng.random() < 0.5 else -1)
    if not on_floor:
        travel = travel + np.array([0, 0, _u(rng, -0.3, 0.3)])
    half = size / 2
    if on_floor:
        base = np.array([mid[0], mid[1], 0.0])
    else:
        base = np.array([mid[0], mid[1], float(np.clip(mid[2], 0.15 + half, 2.2)) - half])
    scale = float(np.clip(_u(rng, 3, 8) * math.sqrt(0.8 / size), 2.0, 14.0))
    obj = {"name": f"{shape}-{i}", "parts": parts, "texture": texture(rng, scale),
           "motion": _motion(rng, base - travel / 2, base + travel / 2, on_floor)}
    return obj, base + [0, 0, half]


def _surface(mesh) -> np.ndarray:
    """Object-frame points on a mover's surface: vertices and seeded samples (deterministic)."""
    import trimesh

    samples, _ = trimesh.sample.sample_surface(mesh, 2000, seed=0)
    return np.concatenate([mesh.vertices, samples])


def _covered(points: np.ndarray, motion: list[dict], times: np.ndarray, cameras: list[np.ndarray], K: np.ndarray) -> int:
    """In how many training frames (one camera per time) object-frame ``points`` under ``motion``
    cover at least ``MIN_PIXELS`` distinct pixels of the ``GRID`` x ``GRID`` image, in front of the
    camera, ignoring occlusion."""
    poses = interpolate_poses([Keyframe(k["t"], k["location"], k["rotation"]) for k in motion], times)
    return sum(_pixel_count(points @ T[:3, :3].T + T[:3, 3], c2w, K) >= MIN_PIXELS for T, c2w in zip(poses, cameras))


def _pixel_count(world: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> int:
    uv, z = project(world, K, c2w)
    ok = (z > 0) & np.all((uv >= 0) & (uv < GRID), axis=1)
    pix = np.floor(uv[ok]).astype(np.int64)
    return len(np.unique(pix[:, 1] * GRID + pix[:, 0]))


def visible_pixels(points: list[np.ndarray], c2w: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels ``(M,)`` of the ``GRID`` x ``GRID`` image where each of M movers is the nearest, from
    their world surface points ``points[k] (P_k, 3)`` seen by camera ``c2w``.

    Each mover's depth image holds its points' nearest depth per pixel. A pixel counts for mover k
    where k has a point and no other mover is nearer, the others' images first grown by one pixel
    (a minimum over 3 x 3): points leave holes in a surface, and a hole must not show what is
    behind it. Growing only the occluders errs towards fewer visible pixels.
    """
    from scipy.ndimage import minimum_filter

    depth = np.full((len(points), GRID, GRID), np.inf)
    for k, world in enumerate(points):
        uv, z = project(world, K, c2w)
        ok = (z > 0) & np.all((uv >= 0) & (uv < GRID), axis=1)
        pix = np.floor(uv[ok]).astype(np.int64)
        np.minimum.at(depth[k], (pix[:, 1], pix[:, 0]), z[ok])
    grown = minimum_filter(depth, size=(1, 3, 3), mode="constant", cval=np.inf)
    out = np.zeros(len(points), dtype=np.int64)
    for k in range(len(points)):
        others = np.delete(grown, k, axis=0).min(axis=0, initial=np.inf)
        out[k] = int(np.count_nonzero(np.isfinite(depth[k]) & (depth[k] < others)))
    return out


def _in_view(path: np.ndarray, radius: float, cameras: list[np.ndarray], K: np.ndarray, width: int) -> int:
    """How many of the training ``cameras`` (one per time of ``path (T, 3)``) see a sphere of
    ``radius`` at the path's point as in view (module docstring: centre inside the image, in front,
    at least ``MIN_EXTENT`` of the width across)."""
    seen = 0
    for c2w, centre in zip(cameras, path):
        (uv,), (z,) = project(centre[None], K, c2w)
        seen += bool(z > 0 and 0 <= uv[0] <= width and 0 <= uv[1] <= width and 2 * radius * K[0, 0] / z >= MIN_EXTENT * width)
    return seen


def _draw(rng: np.random.Generator, seed: int, protocol: str, n: int) -> dict:
    """One candidate spec (plain data) with ``n`` movers, before the checks.

    Each mover is redrawn (up to ``MOVER_TRIES`` times) until its swept bounding sphere keeps clear
    of the movers already placed, of every camera centre and of the room's walls and ceiling:
    without this, scenes of six movers almost never pass the exact checks."""
    rig = _rig(rng, protocol)
    rig_spec = RigSpec(**rig)
    times = np.linspace(0.0, 1.0, rig_spec.times)
    cams = [rig_cameras(rig_spec, t) for t in range(rig_spec.times)]
    eyes = np.concatenate([c[:, :3, 3] for c in cams])
    train = [cams[t][rig_spec.train_view(t)] for t in range(rig_spec.times)]
    K = intrinsics_from_fov(rig_spec.fov, GRID, GRID)
    reach = np.abs(eyes[:, :2]).max(axis=0) + 0.6  # the room holds every camera with a margin
    room_size = np.array([max(_u(rng, 5.5, 8), 2 * reach[0]), max(_u(rng, 5.5, 8), 2 * reach[1]), _u(rng, 2.6, 3.4)])
    objects: list[dict] = []
    mids: list[np.ndarray] = []
    swept: list[tuple[np.ndarray, float]] = []
    floor_movers = set(np.flatnonzero(rng.random(n) < 0.5)) or {int(rng.integers(n))}
    for i in range(n):
        for _ in range(MOVER_TRIES):
            obj, mid = _mover(rng, i, i in floor_movers, rig, mids)
            mesh = _mesh(obj["parts"])  # once per draw: the sphere and the surface both use it
            c, r = _sphere(mesh.vertices)
            path = _centres(obj["motion"], c, times)
            clear = (all(np.linalg.norm(path - p, axis=1).min() > r + q + 0.01 for p, q in swept)
                     and np.linalg.norm(eyes[:, None] - path[None], axis=2).min() > r + 0.05
                     and np.all(np.abs(path[:, :2]) + r < room_size[:2] / 2 - 0.05) and np.all(path[:, 2] + r < room_size[2])
                     and _in_view(path, r, train, K, GRID) >= MIN_VISIBLE_SHARE * len(train)
                     and _covered(_surface(mesh), obj["motion"], times, train, K) >= MIN_VISIBLE_SHARE * len(train))
            if clear:
                break
        objects.append(obj)
        mids.append(mid)
        swept.append((path, r))
    room = {"size": [round(float(x), 3) for x in room_size],
            "floor": texture(rng, _u(rng, 1.5, 3.0)), "walls": texture(rng, _u(rng, 1.2, 2.5))}
    return {"name": f"random-{seed}", "room": room, "objects": objects, "rig": rig, "samples": 1,
            "configs": DEFAULTS["configs"], "resolution": [DEFAULTS["resolution"]] * 2, "seed": seed}


def _family_problem(spec: SceneSpec, on_floor: list[bool]) -> str | None:
    """The family's own acceptance rules (module docstring); ``None`` when the draw passes."""
    built = build_scene(spec)
    scene = built.scene
    K = scene.intrinsics.matrix()
    frames = scene.train_frames
    discs: list[list[tuple[np.ndarray, float] | None]] = []
    cameras = [f.camera_to_world for f in frames]
    grid_K = intrinsics_from_fov(spec.rig.fov, GRID, GRID)
    movers = range(1, len(built.objects))

    def world(k: int, t: int) -> np.ndarray:
        T = scene.objects[k].poses[t]
        return built.objects[k].probe_points @ T[:3, :3].T + T[:3, 3]

    shown = np.stack([visible_pixels([world(k, f.time_index) for k in movers], f.camera_to_world, grid_K) for f in frames])
    for k in movers:
        geom = built.objects[k]
        c_obj, r_obj = geom.bounding_sphere
        path = np.stack([scene.objects[k].poses[f.time_index][:3, :3] @ c_obj + scene.objects[k].poses[f.time_index][:3, 3] for f in frames])
        seen = _in_view(path, r_obj, cameras, K, scene.width)
        if seen < MIN_VISIBLE_SHARE * len(frames):
            return f"{geom.name} in view in {seen} of {len(frames)} training frames"
        covered = int(np.count_nonzero(shown[:, k - 1] >= MIN_PIXELS))
        if covered < MIN_VISIBLE_SHARE * len(frames):
            return f"{geom.name} shows {MIN_PIXELS} pixels unoccluded in {covered} of {len(frames)} training frames"
        row = []
        for f, centre in zip(frames, path):
            (uv,), (z,) = project(centre[None], K, f.camera_to_world)
            row.append((uv, r_obj * K[0, 0] / z) if z > 0 else None)
        discs.append(row)
    if not any(on_floor):
        return "no mover on the floor"
    for a in range(len(discs)):
        for b in range(a + 1, len(discs)):
            for da, db in zip(discs[a], discs[b]):
                if da and db and np.linalg.norm(da[0] - db[0]) < 0.8 * (da[1] + db[1]):
                    return None
    return "no pair of movers passes in front of another"


def random_spec(seed: int, protocol: str = "orbit", max_attempts: int = MAX_ATTEMPTS) -> SceneSpec:
    """The family's scene for ``seed`` (deterministic), checked like any spec.

    Raises:
        SpecError: no draw of ``max_attempts`` passed the checks (names the seed and the last reason).
    """
    if protocol not in RIG_PROTOCOLS:
        raise SpecError(f"--random: unknown protocol {protocol!r} (expected one of {', '.join(RIG_PROTOCOLS)})")
    if seed < 0:
        raise SpecError(f"--random: the seed must be >= 0, got {seed}")
    reason = ""
    # The number of movers comes from the seed alone: redrawing it too would favour the scenes
    # with few movers, which pass the checks more often.
    n = int(np.random.default_rng(seed).integers(MOVERS[0], MOVERS[1] + 1))
    for attempt in range(max_attempts):
        rng = np.random.default_rng([seed, attempt])
        d = _draw(rng, seed, protocol, n)
        on_floor = [all(abs(k["location"][2]) < 1e-12 for k in o["motion"]) for o in d["objects"]]
        try:
            spec = spec_from_dict(d, f"random seed {seed}")
            check_authored_scene(build_scene(spec))
        except SpecError as e:
            reason = str(e).split(": ", 1)[-1]
            continue
        reason = _family_problem(spec, on_floor) or ""
        if not reason:
            return spec
    raise SpecError(f"random seed {seed}: no plausible scene in {max_attempts} draws (last: {reason})")
