"""Scene specs: the YAML files users write and the presets ship (pure Python + numpy).

A spec describes a room (the anchor), rigid foreground objects made of procedural primitive parts
or a mesh file, their keyframed motion, object-space textures, the camera rig and the render and
benchmark settings. ``load_spec`` checks everything that can be checked without geometry and
raises ``SpecError`` with one line naming the file and the field. See docs/benchgen.md.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

PRESET_DIR = Path(__file__).parent / "presets"

#: Primitive part types and their size parameters (all in metres, in the part's own frame).
PART_PARAMS: dict[str, tuple[str, ...]] = {
    "box": ("size",),
    "sphere": ("radius",),
    "cylinder": ("radius", "height"),
    "cone": ("radius", "height"),
    "torus": ("major_radius", "minor_radius"),
    "lathe": ("profile",),
}
TEXTURE_KINDS = ("noise", "checker", "voronoi")
TRAIN_PATHS = ("diagonal", "sweep")
#: Camera rigs: the paper's 15 x 15 arc (``orbit``), a stereo pair (Oxford Multimotion) and a
#: fixed grid of synchronised cameras (NVIDIA Dynamic Scenes). See ``RigSpec``.
RIG_PROTOCOLS = ("orbit", "stereo", "multi-camera")


class SpecError(ValueError):
    """A spec is invalid. The message is one line: ``FILE: field: problem``."""


@dataclass
class Texture:
    """Object-space procedural texture: ``kind`` pattern between two colours (linear RGB)."""

    kind: str = "noise"
    colors: list[list[float]] = field(default_factory=lambda: [[0.8, 0.3, 0.2], [0.15, 0.1, 0.6]])
    scale: float = 4.0
    seed: int | None = None


@dataclass
class Part:
    """A primitive placed in its object's frame (rotation: XYZ Euler angles in degrees)."""

    type: str
    params: dict[str, Any]
    location: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rotation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])


@dataclass
class Keyframe:
    """Object pose at normalised time ``t``: translation and XYZ Euler rotation in degrees."""

    t: float
    location: list[float]
    rotation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])


@dataclass
class ObjectSpec:
    name: str
    parts: list[Part]
    mesh: str | None
    mesh_scale: float
    texture: Texture
    keyframes: list[Keyframe]


@dataclass
class RoomSpec:
    """Closed box room ``[-x/2, x/2] x [-y/2, y/2] x [0, z]``; textures for floor and walls."""

    size: list[float]
    floor: Texture
    walls: Texture


@dataclass
class RigSpec:
    """The cameras: ``views`` camera positions x ``times`` timestamps, in one of three protocols.

    ``orbit`` (the paper's Dynamic Indoor Scene protocol): viewpoint v sits at angle
    ``arc[0] + v (arc[1] - arc[0]) / (views - 1)`` degrees (0 = -y axis, counter-clockwise), at
    ``radius`` from the target and height ``height``, looking at ``target``. The training camera
    at timestamp t is viewpoint ``t % views`` (``diagonal``) or ``round(t (views - 1) / (times -
    1))`` (``sweep``: one pass along the arc); every other (view, time) pair is a test view.

    ``stereo`` (Oxford Multimotion): a parallel pair ``baseline`` metres apart; the left camera
    (view 0) moves along the arc from ``arc[0]`` to ``arc[1]`` over the video (equal angles: a
    static camera) and films the training video; the right camera (view 1) gives the test views.

    ``multi-camera`` (NVIDIA Dynamic Scenes): ``grid`` = [rows, cols] fixed cameras ``spacing``
    metres apart on the plane facing the target from the arc's middle angle, each looking at the
    target; view ``r * cols + c``. Camera 0 is the test camera at every timestamp; the training
    camera at t follows ``train_path`` over cameras 1..views-1 (NVIDIA's protocol trains on
    camera t mod 12, which takes camera 0 at t = 0; keeping it out lets the test split start at
    t = 0, which D-NeRF's loader requires, and gives one test view per timestamp).

    ``test_views`` > 0 keeps only that many test frames, evenly spread in (time, view) order.
    """

    protocol: str = "orbit"
    views: int = 15
    times: int = 15
    fov: float = 60.0
    radius: float = 2.6
    height: float = 1.5
    arc: list[float] = field(default_factory=lambda: [-40.0, 40.0])
    target: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.6])
    train_path: str = "diagonal"
    test_views: int = 0
    baseline: float = 0.2
    grid: list[int] = field(default_factory=lambda: [2, 6])
    spacing: float = 0.25

    def train_view(self, t: int) -> int:
        if self.protocol == "stereo":
            return 0
        first, n = (1, self.views - 1) if self.protocol == "multi-camera" else (0, self.views)
        if self.train_path == "diagonal":
            return first + t % n
        return first + (0 if self.times == 1 else round(t * (n - 1) / (self.times - 1)))

    def is_test(self, view: int, t: int) -> bool:
        """Whether the camera ``view`` at timestamp ``t`` is a test view (before ``test_views``)."""
        if view == self.train_view(t):
            return False
        return view == 0 if self.protocol == "multi-camera" else True


@dataclass
class SceneSpec:
    name: str
    room: RoomSpec
    objects: list[ObjectSpec]
    rig: RigSpec
    resolution: list[int] = field(default_factory=lambda: [128, 128])
    samples: int = 1
    configs: int = 50
    margin: float = 0.05
    scale_range: list[float] = field(default_factory=lambda: [0.3, 3.0])
    candidates: int = 4000
    seed: int = 0
    source: str = "<spec>"

    @property
    def width(self) -> int:
        return self.resolution[0]

    @property
    def height(self) -> int:
        return self.resolution[1]

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (round-trips through ``spec_from_dict``); mesh paths are absolute."""
        d = asdict(self)
        d.pop("source")
        for o, od in zip(self.objects, d["objects"]):
            od["motion"] = od.pop("keyframes")
            od["parts"] = [{"type": p.type, **p.params, "location": p.location, "rotation": p.rotation} for p in o.parts] or None
            for k in ("parts", "mesh"):
                if od[k] is None:
                    del od[k]
        return d

    def with_overrides(self, **kw: Any) -> "SceneSpec":
        """Copy with top-level settings replaced (``None`` values are ignored); re-checked."""
        d = self.to_dict()
        for k, v in kw.items():
            if v is None:
                continue
            if k == "resolution" and isinstance(v, int):
                v = [v, v]
            d[k] = v
        return spec_from_dict(d, self.source)


# --------------------------------------------------------------------------------------------
# Parsing helpers: every error names the file and the field path.
# --------------------------------------------------------------------------------------------


class _Ctx:
    def __init__(self, source: str, base_dir: Path):
        self.source = source
        self.base_dir = base_dir

    def fail(self, where: str, msg: str) -> SpecError:
        return SpecError(f"{self.source}: {where}: {msg}")

    def mapping(self, d: Any, where: str, allowed: set[str]) -> dict[str, Any]:
        if not isinstance(d, dict):
            raise self.fail(where, f"expected a mapping, got {type(d).__name__}")
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise self.fail(f"{where}.{unknown[0]}" if where else unknown[0], f"unknown field (allowed: {', '.join(sorted(allowed))})")
        return d

    def number(self, v: Any, where: str, lo: float | None = None, hi: float | None = None, strict_lo: bool = False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(where, f"expected a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail(where, f"must be a finite number, got {v}")
        if lo is not None and (v < lo or (strict_lo and v == lo)):
            raise self.fail(where, f"must be {'>' if strict_lo else '>='} {lo}, got {v}")
        if hi is not None and v > hi:
            raise self.fail(where, f"must be <= {hi}, got {v}")
        return v

    def integer(self, v: Any, where: str, lo: int, hi: int | None = None) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, f"expected an integer, got {v!r}")
        if v < lo:
            raise self.fail(where, f"must be >= {lo}, got {v}")
        if hi is not None and v > hi:
            raise self.fail(where, f"must be <= {hi:,}, got {v:,}")
        return v

    def vector(self, v: Any, where: str, n: int, positive: bool = False) -> list[float]:
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise self.fail(where, f"expected a list of {n} numbers, got {v!r}")
        return [self.number(x, f"{where}[{i}]", lo=0.0 if positive else None, strict_lo=positive) for i, x in enumerate(v)]


def _texture(c: _Ctx, d: Any, where: str, default_colors: list[list[float]] | None = None) -> Texture:
    d = c.mapping(d or {}, where, {"kind", "colors", "scale", "seed"})
    kind = d.get("kind", "noise")
    if kind not in TEXTURE_KINDS:
        raise c.fail(f"{where}.kind", f"unknown texture kind {kind!r} (expected one of {', '.join(TEXTURE_KINDS)})")
    colors = d.get("colors", default_colors or Texture().colors)
    if not isinstance(colors, list) or len(colors) != 2:
        raise c.fail(f"{where}.colors", "expected two RGB colours")
    colors = [[c.number(x, f"{where}.colors[{i}][{j}]", 0.0, 1.0) for j, x in enumerate(c.vector(col, f"{where}.colors[{i}]", 3))] for i, col in enumerate(colors)]
    seed = d.get("seed")
    if seed is not None:
        seed = c.integer(seed, f"{where}.seed", 0)
    return Texture(kind, colors, c.number(d.get("scale", 4.0), f"{where}.scale", 0.0, strict_lo=True), seed)


#: Most points of a lathe profile: enough for cups, vases and rings, few enough that checking it
#: for self-intersections (every pair of edges) stays instant.
MAX_PROFILE_POINTS = 64


def _segments_cross(p: list[float], q: list[float], a: list[float], b: list[float]) -> bool:
    """Whether the closed segments ``pq`` and ``ab`` of the plane intersect (touching included)."""
    def orient(u: list[float], v: list[float], w: list[float]) -> float:
        return (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])

    def on(u: list[float], v: list[float], w: list[float]) -> bool:
        return min(u[0], v[0]) <= w[0] <= max(u[0], v[0]) and min(u[1], v[1]) <= w[1] <= max(u[1], v[1])

    d1, d2, d3, d4 = orient(a, b, p), orient(a, b, q), orient(p, q, a), orient(p, q, b)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0 not in (d1, d2, d3, d4):
        return True
    return (d1 == 0 and on(a, b, p)) or (d2 == 0 and on(a, b, q)) or (d3 == 0 and on(p, q, a)) or (d4 == 0 and on(p, q, b))


def _profile(c: _Ctx, v: Any, where: str) -> list[list[float]]:
    """A lathe profile: a simple polygon of ``[r, z]`` points in the half-plane r >= 0 (closed from
    the last point back to the first), at least 3 points, non-zero area, no edges crossing."""
    if not isinstance(v, list) or not 3 <= len(v) <= MAX_PROFILE_POINTS:
        raise c.fail(where, f"expected a list of 3 to {MAX_PROFILE_POINTS} [r, z] points")
    pts = [c.vector(x, f"{where}[{i}]", 2) for i, x in enumerate(v)]
    for i, (r, _) in enumerate(pts):
        if r < 0:
            raise c.fail(f"{where}[{i}]", f"the radius must be >= 0, got {r}")
    n = len(pts)
    area = 0.5 * sum(pts[i][0] * pts[(i + 1) % n][1] - pts[(i + 1) % n][0] * pts[i][1] for i in range(n))
    if abs(area) < 1e-12:
        raise c.fail(where, "the profile encloses no area")
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbouring edges share a point
            if _segments_cross(pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]):
                raise c.fail(where, f"edges {i} and {j} of the profile cross (it must be a simple polygon)")
    return pts


def _part(c: _Ctx, d: Any, where: str) -> Part:
    if not isinstance(d, dict):
        raise c.fail(where, "expected a mapping")
    ptype = d.get("type")
    if ptype not in PART_PARAMS:
        raise c.fail(f"{where}.type", f"unknown object type {ptype!r} (expected one of {', '.join(PART_PARAMS)})")
    params = PART_PARAMS[ptype]
    c.mapping(d, where, {"type", "location", "rotation", *params})
    values: dict[str, Any] = {}
    for p in params:
        if p not in d:
            raise c.fail(f"{where}.{p}", f"missing (a {ptype} needs {', '.join(params)})")
        if p == "profile":
            values[p] = _profile(c, d[p], f"{where}.{p}")
        else:
            values[p] = c.vector(d[p], f"{where}.{p}", 3, positive=True) if p == "size" else c.number(d[p], f"{where}.{p}", 0.0, strict_lo=True)
    if ptype == "torus" and values["minor_radius"] >= values["major_radius"]:
        raise c.fail(f"{where}.minor_radius", "must be smaller than major_radius")
    return Part(ptype, values, c.vector(d.get("location", [0, 0, 0]), f"{where}.location", 3), c.vector(d.get("rotation", [0, 0, 0]), f"{where}.rotation", 3))


def _object(c: _Ctx, d: Any, where: str, index: int) -> ObjectSpec:
    d = c.mapping(d, where, {"name", "parts", "mesh", "mesh_scale", "texture", "motion"})
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise c.fail(f"{where}.name", "missing or not a string")
    where = f"objects[{index}] ({name})"
    parts_d, mesh = d.get("parts"), d.get("mesh")
    if (parts_d is None) == (mesh is None):
        raise c.fail(where, "give exactly one of 'parts' (primitives) or 'mesh' (a file trimesh can load)")
    parts: list[Part] = []
    if parts_d is not None:
        if not isinstance(parts_d, list) or not parts_d:
            raise c.fail(f"{where}.parts", "expected a non-empty list")
        parts = [_part(c, p, f"{where}.parts[{i}]") for i, p in enumerate(parts_d)]
    if mesh is not None:
        path = Path(mesh)
        path = path if path.is_absolute() else c.base_dir / path
        if not path.is_file():
            raise c.fail(f"{where}.mesh", f"mesh file {str(path)!r} not found")
        mesh = str(path.resolve())
    motion = d.get("motion")
    if not isinstance(motion, list) or not motion:
        raise c.fail(f"{where}.motion", "expected a non-empty list of keyframes {t, location, rotation}")
    keys = []
    for i, k in enumerate(motion):
        kw = f"{where}.motion[{i}]"
        k = c.mapping(k, kw, {"t", "location", "rotation"})
        if "t" not in k or "location" not in k:
            raise c.fail(kw, "a keyframe needs 't' and 'location'")
        keys.append(Keyframe(c.number(k["t"], f"{kw}.t", 0.0, 1.0), c.vector(k["location"], f"{kw}.location", 3), c.vector(k.get("rotation", [0, 0, 0]), f"{kw}.rotation", 3)))
    ts = [k.t for k in keys]
    if any(b <= a for a, b in zip(ts, ts[1:])):
        raise c.fail(f"{where}.motion", f"keyframe times must strictly increase, got {ts}")
    return ObjectSpec(name, parts, mesh, c.number(d.get("mesh_scale", 1.0), f"{where}.mesh_scale", 0.0, strict_lo=True), _texture(c, d.get("texture"), f"{where}.texture"), keys)


#: Upper bounds of a spec's sizes: an 8K frame, Cycles' own sample ceiling in practice, and
#: ground truths by the thousand; above them a typo would render for days or fill the disk.
MAX_RESOLUTION = 8192
MAX_CYCLES_SAMPLES = 65536
MAX_CONFIGS = 10_000

TOP_FIELDS = {"name", "room", "objects", "rig", "resolution", "samples", "configs", "margin", "scale_range", "candidates", "seed"}


def _room(c: _Ctx, d: Any) -> RoomSpec:
    room_d = c.mapping(d, "room", {"size", "floor", "walls"})
    if "size" not in room_d:
        raise c.fail("room.size", "missing")
    return RoomSpec(
        c.vector(room_d["size"], "room.size", 3, positive=True),
        _texture(c, room_d.get("floor"), "room.floor", [[0.75, 0.7, 0.6], [0.3, 0.25, 0.2]]),
        _texture(c, room_d.get("walls"), "room.walls", [[0.6, 0.7, 0.75], [0.2, 0.3, 0.35]]),
    )


def _objects(c: _Ctx, objs_d: Any) -> list[ObjectSpec]:
    if not isinstance(objs_d, list) or not objs_d:
        raise c.fail("objects", "expected a non-empty list")
    if len(objs_d) > 254:
        raise c.fail("objects", f"{len(objs_d)} objects; at most 254 fit in 8-bit ids with the room")
    objects = [_object(c, o, f"objects[{i}]", i) for i, o in enumerate(objs_d)]
    names = [o.name for o in objects]
    dup = sorted({n for n in names if names.count(n) > 1} | ({"room"} & set(names)))
    if dup:
        raise c.fail("objects", f"duplicate or reserved object name {dup[0]!r}")
    return objects


def _rig(c: _Ctx, d: Any) -> RigSpec:
    rd = c.mapping(d, "rig", set(RigSpec.__dataclass_fields__))
    r = RigSpec()
    protocol = rd.get("protocol", r.protocol)
    if protocol not in RIG_PROTOCOLS:
        raise c.fail("rig.protocol", f"unknown protocol {protocol!r} (expected one of {', '.join(RIG_PROTOCOLS)})")
    grid = rd.get("grid", r.grid)
    if not isinstance(grid, list) or len(grid) != 2:
        raise c.fail("rig.grid", f"expected [rows, cols], got {grid!r}")
    grid = [c.integer(x, f"rig.grid[{i}]", 1) for i, x in enumerate(grid)]
    # The protocol fixes the number of cameras; a contradicting `views` is an error, not ignored.
    implied = {"stereo": 2, "multi-camera": grid[0] * grid[1]}.get(protocol)
    if implied is not None and rd.get("views", implied) != implied:
        raise c.fail("rig.views", f"the {protocol} protocol has {implied} cameras; leave 'views' out or set it to {implied}")
    rig = RigSpec(
        protocol=protocol,
        views=c.integer(rd.get("views", implied or r.views), "rig.views", 1),
        times=c.integer(rd.get("times", r.times), "rig.times", 1),
        fov=c.number(rd.get("fov", r.fov), "rig.fov", 1.0, 170.0),
        radius=c.number(rd.get("radius", r.radius), "rig.radius", 0.0, strict_lo=True),
        height=c.number(rd.get("height", r.height), "rig.height"),
        arc=c.vector(rd.get("arc", r.arc), "rig.arc", 2),
        target=c.vector(rd.get("target", r.target), "rig.target", 3),
        train_path=rd.get("train_path", r.train_path),
        test_views=c.integer(rd.get("test_views", r.test_views), "rig.test_views", 0),
        baseline=c.number(rd.get("baseline", r.baseline), "rig.baseline", 0.0, strict_lo=True),
        grid=grid,
        spacing=c.number(rd.get("spacing", r.spacing), "rig.spacing", 0.0, strict_lo=True),
    )
    if rig.train_path not in TRAIN_PATHS:
        raise c.fail("rig.train_path", f"unknown path {rig.train_path!r} (expected one of {', '.join(TRAIN_PATHS)})")
    if rig.views < 2:  # the training video takes one view per time; test views need another
        raise c.fail("rig.views", f"needs at least 2 camera positions so that there are test views, got {rig.views}")
    if not any(rig.is_test(v, t) for t in range(rig.times) for v in range(rig.views)):
        raise c.fail("rig", f"the {rig.protocol} rig has no test view")
    return rig


def _resolution(c: _Ctx, res: Any) -> list[int]:
    res = [res, res] if isinstance(res, int) and not isinstance(res, bool) else res
    if not isinstance(res, list) or len(res) != 2:
        raise c.fail("resolution", f"expected an integer or [width, height], got {res!r}")
    return [c.integer(x, f"resolution[{i}]", 4, MAX_RESOLUTION) for i, x in enumerate(res)]


def spec_from_dict(d: Any, source: str = "<spec>", base_dir: Path | None = None) -> SceneSpec:
    """Build and check a ``SceneSpec`` from plain data; ``SpecError`` names ``source`` and the field."""
    c = _Ctx(source, base_dir or Path.cwd())
    d = c.mapping(d, "", TOP_FIELDS)
    for req in ("room", "objects"):
        if req not in d:
            raise c.fail(req, "missing")
    room, objects, rig = _room(c, d["room"]), _objects(c, d["objects"]), _rig(c, d.get("rig", {}))
    scale_range = c.vector(d.get("scale_range", [0.3, 3.0]), "scale_range", 2, positive=True)
    if not scale_range[0] < 1.0 < scale_range[1]:
        raise c.fail("scale_range", f"must contain 1 strictly inside, got {scale_range}")
    spec = SceneSpec(
        name=str(d.get("name", Path(source).stem)),
        room=room,
        objects=objects,
        rig=rig,
        resolution=_resolution(c, d.get("resolution", [128, 128])),
        samples=c.integer(d.get("samples", 1), "samples", 1, MAX_CYCLES_SAMPLES),
        configs=c.integer(d.get("configs", 50), "configs", 1, MAX_CONFIGS),
        margin=c.number(d.get("margin", 0.05), "margin", 0.0),
        scale_range=scale_range,
        candidates=c.integer(d.get("candidates", 4000), "candidates", 1),
        seed=c.integer(d.get("seed", 0), "seed", 0),
        source=source,
    )
    if spec.candidates < spec.configs:
        raise c.fail("candidates", f"{spec.candidates} candidates cannot give {spec.configs} configurations")
    return spec


def load_spec(path: str | Path) -> SceneSpec:
    """Load and check a spec file (relative mesh paths are resolved against its directory)."""
    path = Path(path)
    return spec_from_dict(read_spec_yaml(path), str(path), path.parent)


def read_spec_yaml(path: Path) -> Any:
    """The parsed YAML of a spec file; ``SpecError`` naming the file if missing or not YAML."""
    if not path.is_file():
        raise SpecError(f"{path}: spec file not found")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SpecError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def load_preset(name: str) -> SceneSpec:
    path = PRESET_DIR / f"{name}.yaml"
    if not path.is_file():
        raise SpecError(f"unknown preset {name!r} (available: {', '.join(preset_names())})")
    return load_spec(path)


def dump_spec(spec: SceneSpec) -> str:
    """YAML text of a spec (what ``spec.yaml`` in a dataset holds)."""
    return yaml.safe_dump(copy.deepcopy(spec.to_dict()), sort_keys=False)
