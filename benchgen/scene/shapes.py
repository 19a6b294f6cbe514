"""The procedural family's vocabulary of mover shapes and textures (numpy + trimesh).

Each shape function draws, from ``rng``, the parts (spec dicts) of an object of extent about 1
with its base near z = 0; :func:`normalised` puts the base at z = 0 and scales the largest
extent to the mover's size, on the tessellated meshes the renderer and the room check use.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from benchgen.scene.geometry import part_mesh
from benchgen.scene.spec import TEXTURE_KINDS, Part


def uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """One draw uniform in ``[lo, hi)`` as a Python float."""
    return float(rng.uniform(lo, hi))


def _block(rng: np.random.Generator) -> list[dict]:
    size = [uniform(rng, 0.3, 1.0), uniform(rng, 0.3, 1.0), uniform(rng, 0.3, 1.0)]
    if rng.random() < 0.4:  # a thin plate
        size[int(rng.integers(3))] = uniform(rng, 0.04, 0.1)
    return [{"type": "box", "size": size, "location": [0, 0, size[2] / 2]}]


def _ball(rng: np.random.Generator) -> list[dict]:
    return [{"type": "sphere", "radius": 0.5, "location": [0, 0, 0.5]}]


def _can(rng: np.random.Generator) -> list[dict]:
    r, h = (uniform(rng, 0.03, 0.07), 1.0) if rng.random() < 0.4 else (uniform(rng, 0.2, 0.5), uniform(rng, 0.4, 1.0))  # a thin rod or a can
    return [{"type": "cylinder", "radius": r, "height": h, "location": [0, 0, h / 2]}]


def _cone(rng: np.random.Generator) -> list[dict]:
    r, h = uniform(rng, 0.25, 0.5), uniform(rng, 0.5, 1.0)
    return [{"type": "cone", "radius": r, "height": h, "location": [0, 0, h / 2]}]


def _ring(rng: np.random.Generator) -> list[dict]:
    R = 0.4
    r = R * uniform(rng, 0.12, 0.45)
    standing = rng.random() < 0.5  # a hoop standing on its rim, or a ring lying flat
    return [{"type": "torus", "major_radius": R, "minor_radius": r,
             "location": [0, 0, R + r if standing else r], "rotation": [90, 0, 0] if standing else [0, 0, 0]}]


def _cup(rng: np.random.Generator) -> list[dict]:
    r, h, wall = uniform(rng, 0.25, 0.45), uniform(rng, 0.4, 1.0), uniform(rng, 0.03, 0.08)
    flare = uniform(rng, 1.0, 1.3)
    profile = [[0, 0], [r, 0], [r * flare, h], [r * flare - wall, h], [r - wall, wall], [0, wall]]
    return [{"type": "lathe", "profile": profile}]


def _vase(rng: np.random.Generator) -> list[dict]:
    r0, r1, r2, h = uniform(rng, 0.15, 0.3), uniform(rng, 0.3, 0.5), uniform(rng, 0.08, 0.2), uniform(rng, 0.6, 1.0)
    profile = [[0, 0], [r0, 0], [r1, 0.4 * h], [r2, 0.85 * h], [r2 * 1.3, h], [0, h]]
    return [{"type": "lathe", "profile": profile}]


def _washer(rng: np.random.Generator) -> list[dict]:
    ro, t = 0.5, uniform(rng, 0.05, 0.25)
    ri = ro * uniform(rng, 0.3, 0.7)
    return [{"type": "lathe", "profile": [[ri, 0], [ro, 0], [ro, t], [ri, t]]}]


def _table(rng: np.random.Generator) -> list[dict]:
    w, d, h, top, leg = uniform(rng, 0.6, 1.0), uniform(rng, 0.4, 0.8), uniform(rng, 0.4, 0.8), uniform(rng, 0.03, 0.07), uniform(rng, 0.02, 0.05)
    parts = [{"type": "box", "size": [w, d, top], "location": [0, 0, h - top / 2]}]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append({"type": "cylinder", "radius": leg, "height": h - top,
                          "location": [sx * (w / 2 - 2 * leg), sy * (d / 2 - 2 * leg), (h - top) / 2]})
    return parts


def _arch(rng: np.random.Generator) -> list[dict]:
    w, h, t, d = uniform(rng, 0.5, 1.0), uniform(rng, 0.5, 1.0), uniform(rng, 0.06, 0.15), uniform(rng, 0.1, 0.3)
    return [{"type": "box", "size": [t, d, h], "location": [-(w - t) / 2, 0, h / 2]},
            {"type": "box", "size": [t, d, h], "location": [(w - t) / 2, 0, h / 2]},
            {"type": "box", "size": [w, d, t], "location": [0, 0, h + t / 2]}]


def _lamp(rng: np.random.Generator) -> list[dict]:
    rb, tb, rod, h, shade = uniform(rng, 0.15, 0.3), uniform(rng, 0.03, 0.06), uniform(rng, 0.015, 0.03), uniform(rng, 0.5, 0.9), uniform(rng, 0.15, 0.3)
    return [{"type": "cylinder", "radius": rb, "height": tb, "location": [0, 0, tb / 2]},
            {"type": "cylinder", "radius": rod, "height": h, "location": [0, 0, tb + h / 2]},
            {"type": "cone", "radius": shade, "height": shade, "location": [0, 0, tb + h]}]


def _l_shape(rng: np.random.Generator) -> list[dict]:
    a, b, t, d = uniform(rng, 0.5, 1.0), uniform(rng, 0.4, 0.9), uniform(rng, 0.1, 0.25), uniform(rng, 0.2, 0.6)
    return [{"type": "box", "size": [a, d, t], "location": [a / 2, 0, t / 2]},
            {"type": "box", "size": [t, d, b], "location": [t / 2, 0, b / 2]}]


#: The vocabulary; names become the movers' names (with an index).
SHAPES: dict[str, Callable[[np.random.Generator], list[dict]]] = {
    "block": _block, "ball": _ball, "can": _can, "cone": _cone, "ring": _ring, "cup": _cup, "vase": _vase,
    "washer": _washer, "table": _table, "arch": _arch, "lamp": _lamp, "l-shape": _l_shape,
}


def _scaled_part(p: dict, s: float, shift: np.ndarray) -> dict:
    """Part dict ``p`` scaled by ``s`` about the object origin after translating by ``shift``."""
    out = {k: v for k, v in p.items()}
    out["location"] = [float(x) for x in (np.asarray(p.get("location", [0, 0, 0]), dtype=np.float64) + shift) * s]
    for k in ("radius", "height", "major_radius", "minor_radius"):
        if k in p:
            out[k] = float(p[k] * s)
    if "size" in p:
        out["size"] = [float(x * s) for x in p["size"]]
    if "profile" in p:
        out["profile"] = [[float(r * s), float(z * s)] for r, z in p["profile"]]
    return out


def normalised(parts: list[dict], size: float) -> list[dict]:
    """Parts moved so that the tessellated object's base is at z = 0 and its footprint centred at
    the origin, and scaled so that its largest extent is ``size`` (the meshes the renderer and the
    room check use, so a floor mover touches the floor exactly)."""
    def mesh_bounds(ps: list[dict]) -> np.ndarray:
        meshes = [part_dict_mesh(p) for p in ps]
        return np.array([np.min([m.bounds[0] for m in meshes], axis=0), np.max([m.bounds[1] for m in meshes], axis=0)])

    lo, hi = mesh_bounds(parts)
    shift = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    out = [_scaled_part(p, size / float(np.max(hi - lo)), shift) for p in parts]
    base = mesh_bounds(out)[0][2]  # tessellation rounding after the scale
    for p in out:
        p["location"][2] -= float(base)
    return out


def _colour_pair(rng: np.random.Generator) -> list[list[float]]:
    """Two colours that differ in brightness, so every surface has texture to match; drawn
    uniformly in display (sRGB) values and stored linear, as the spec's colours are."""
    a = rng.uniform(0.05, 0.95, 3)
    b = rng.uniform(0.05, 0.95, 3)
    if abs(a.mean() - b.mean()) < 0.3:
        b = np.clip(1.0 - a + rng.uniform(-0.1, 0.1, 3), 0.05, 0.95)
    return [[round(float(x) ** 2.2, 4) for x in c] for c in (a, b)]


def texture(rng: np.random.Generator, scale: float) -> dict:
    """A texture spec dict: a random kind, two colours of different brightness, ``scale``."""
    return {"kind": str(rng.choice(TEXTURE_KINDS)), "colors": _colour_pair(rng), "scale": round(scale, 3)}


def part_dict_mesh(p: dict):
    """The tessellated mesh of part spec dict ``p``, as the renderer builds it."""
    return part_mesh(Part(p["type"], {k: p[k] for k in p if k not in ("type", "location", "rotation")},
                          p.get("location", [0, 0, 0]), p.get("rotation", [0, 0, 0])))
