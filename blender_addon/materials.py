"""Blender materials of an imported export (bpy): the volumes' emission-absorption node trees that
evaluate each learned field's activations as OSN does, its colour planes as images, and the
preview meshes' vertex-colour emission."""

from __future__ import annotations

import math
from typing import Any

import bpy
import numpy as np

from ._kernel import export_format as core

#: Object property the volume material multiplies its density by: 1 / the object's scale (set by
#: ``scene_build``), so the optical depth along a ray stays the same at any scale.
P_INV = "osn_inv_scale"


def _node_tree(mat: bpy.types.Material) -> bpy.types.NodeTree:
    if mat.node_tree is None:  # Blender < 5.0 creates the tree on demand
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    return nt


def _math(nt: bpy.types.NodeTree, op: str, a: Any, b: Any = None) -> Any:
    """A Math node ``op(a, b)``; ``a``/``b`` are sockets or numbers. Returns its output socket."""
    node = nt.nodes.new("ShaderNodeMath")
    node.operation = op
    for i, v in enumerate((a, b)):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            node.inputs[i].default_value = float(v)
        else:
            nt.links.new(v, node.inputs[i])
    return node.outputs[0]


def _attribute(nt: bpy.types.NodeTree, name: str, kind: str = "GEOMETRY") -> bpy.types.Node:
    node = nt.nodes.new("ShaderNodeAttribute")
    node.attribute_type, node.attribute_name = kind, name
    return node


def _softplus(nt: bpy.types.NodeTree, x: Any) -> Any:
    """``log(1 + exp(x))`` as ``max(x, 0) + log(1 + exp(-|x|))``: finite for any ``x``."""
    tail = _math(nt, "LOGARITHM", _math(nt, "ADD", _math(nt, "EXPONENT", _math(nt, "MULTIPLY", _math(nt, "ABSOLUTE", x), -1.0)), 1.0), math.e)
    return _math(nt, "ADD", _math(nt, "MAXIMUM", x, 0.0), tail)


def _sigmoid_rgb(nt: bpy.types.NodeTree, v: Any) -> Any:
    """Per-channel ``1 / (1 + exp(-v))`` of a vector socket; returns a colour socket."""
    sep, comb = nt.nodes.new("ShaderNodeSeparateXYZ"), nt.nodes.new("ShaderNodeCombineColor")
    nt.links.new(v, sep.inputs[0])
    for i in range(3):
        e = _math(nt, "EXPONENT", _math(nt, "MULTIPLY", sep.outputs[i], -1.0))
        nt.links.new(_math(nt, "DIVIDE", 1.0, _math(nt, "ADD", e, 1.0)), comb.inputs[i])
    return comb.outputs[0]


def _inside_box(nt: bpy.types.NodeTree, bbox: np.ndarray) -> Any:
    """1 inside the object-space box ``bbox (2, 3)``, 0 outside: the field is cut at its box,
    while Blender's trilinear lookups fade each grid out over one voxel beyond its last node."""
    lo, hi = np.asarray(bbox, dtype=np.float64)
    tc = nt.nodes.new("ShaderNodeTexCoord")
    rel = nt.nodes.new("ShaderNodeVectorMath")
    rel.operation = "SUBTRACT"
    nt.links.new(tc.outputs["Object"], rel.inputs[0])
    rel.inputs[1].default_value = tuple((lo + hi) / 2.0)
    dist = nt.nodes.new("ShaderNodeVectorMath")
    dist.operation = "ABSOLUTE"
    nt.links.new(rel.outputs[0], dist.inputs[0])
    out = nt.nodes.new("ShaderNodeVectorMath")
    out.operation = "SUBTRACT"
    nt.links.new(dist.outputs[0], out.inputs[0])
    out.inputs[1].default_value = tuple((hi - lo) / 2.0)
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(out.outputs[0], sep.inputs[0])
    return _math(nt, "LESS_THAN", _math(nt, "MAXIMUM", _math(nt, "MAXIMUM", sep.outputs[0], sep.outputs[1]), sep.outputs[2]), 0.0)


def plane_images(name: str, planes: np.ndarray) -> list[bpy.types.Image]:
    """The colour planes ``(3, P, P, 3)`` as float images (``planes[i, v, u]`` at pixel column u,
    row v from the bottom), non-colour data, packed into the .blend."""
    images = []
    P = planes.shape[1]
    for i, axes in enumerate(core.PLANE_AXES):
        img = bpy.data.images.new(f"{name} plane {'xyz'[axes[0]]}{'xyz'[axes[1]]}", P, P, alpha=True, float_buffer=True)
        img.colorspace_settings.name = "Non-Color"
        rgba = np.concatenate([planes[i], np.ones((P, P, 1))], axis=-1).astype(np.float32)
        img.pixels.foreach_set(rgba.ravel())
        img.pack()
        images.append(img)
    return images


def _plane_colour(nt: bpy.types.NodeTree, images: list[bpy.types.Image], bbox: np.ndarray) -> Any:
    """Sum of the colour planes' bilinear lookups at the shading point: texel j of a plane of
    side P sits at box-normalised ``-1 + 2 j / (P - 1)`` (the field's corner-aligned lookups),
    so object coordinate ``x`` maps to texture coordinate ``(x - lo) / (hi - lo) * (P - 1) / P +
    0.5 / P`` (Blender's linear interpolation puts texel centres at ``(j + 0.5) / P``)."""
    lo, hi = np.asarray(bbox, dtype=np.float64)
    P = images[0].size[0]
    scale = (P - 1) / (P * (hi - lo))
    tc = nt.nodes.new("ShaderNodeTexCoord")
    uvw = nt.nodes.new("ShaderNodeVectorMath")
    uvw.operation = "MULTIPLY_ADD"
    nt.links.new(tc.outputs["Object"], uvw.inputs[0])
    uvw.inputs[1].default_value = tuple(scale)
    uvw.inputs[2].default_value = tuple(0.5 / P - lo * scale)
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(uvw.outputs[0], sep.inputs[0])
    total = None
    for img, (a, b) in zip(images, core.PLANE_AXES):
        uv = nt.nodes.new("ShaderNodeCombineXYZ")
        nt.links.new(sep.outputs[a], uv.inputs[0])
        nt.links.new(sep.outputs[b], uv.inputs[1])
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image, tex.interpolation, tex.extension = img, "Linear", "EXTEND"
        nt.links.new(uv.outputs[0], tex.inputs["Vector"])
        if total is None:
            total = tex.outputs["Color"]
            continue
        add = nt.nodes.new("ShaderNodeVectorMath")
        add.operation = "ADD"
        nt.links.new(total, add.inputs[0])
        nt.links.new(tex.outputs["Color"], add.inputs[1])
        total = add.outputs[0]
    return total


def volume_material(name: str, obj: core.ExportObjectData | None = None, planes: list[bpy.types.Image] | None = None
                    ) -> bpy.types.Material:
    """Emission-absorption (the NeRF rendering model): absorption ``sigma`` and emission ``sigma * c``.

    With the object's field grids (``obj.field``), ``sigma`` and ``c`` are the learned field's:
    ``softplus`` of the trilinear pre-activation density inside the box, ``sigmoid`` of the raw
    colour plus its colour planes (``planes``, :func:`plane_images`), ``c`` display-referred as OSN composites it (the import sets the
    Raw view transform so the render is not encoded again). Without them (an older export) the
    node values ``density`` and linear ``color`` are used, ``color`` brought back to display values
    by a 2.2 gamma. ``sigma`` is per object unit; the volume's density space is World and
    ``sigma`` is multiplied by the object's ``osn_inv_scale``: an object scaled by ``s`` is ``s``
    times longer along every ray, so the optical depth, and with it the training-camera image,
    stays unchanged.
    """
    mat = bpy.data.materials.new(name)
    nt = _node_tree(mat)
    n, link = nt.nodes, nt.links.new
    out = n.new("ShaderNodeOutputMaterial")
    inv = _attribute(nt, P_INV, "OBJECT")
    f = obj.field if obj is not None else None
    if f is not None:
        raw = _attribute(nt, f.density_grid).outputs["Fac"]
        sigma = _math(nt, "MULTIPLY", _softplus(nt, _math(nt, "ADD", raw, f.density_offset)), _inside_box(nt, obj.bbox))
        colour_raw = _attribute(nt, f.color_grid).outputs["Vector"]
        if planes:
            add = n.new("ShaderNodeVectorMath")
            add.operation = "ADD"
            link(colour_raw, add.inputs[0])
            link(_plane_colour(nt, planes, obj.bbox), add.inputs[1])
            colour_raw = add.outputs[0]
        colour = _sigmoid_rgb(nt, colour_raw)
    else:
        sigma = _attribute(nt, "density").outputs["Fac"]
        gamma = n.new("ShaderNodeGamma")
        link(_attribute(nt, "color").outputs["Color"], gamma.inputs["Color"])
        gamma.inputs["Gamma"].default_value = 1.0 / 2.2
        colour = gamma.outputs[0]
    sigma = _math(nt, "MULTIPLY", sigma, inv.outputs["Fac"])
    absorb, emit, add = n.new("ShaderNodeVolumeAbsorption"), n.new("ShaderNodeEmission"), n.new("ShaderNodeAddShader")
    absorb.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)  # Cycles absorbs (1 - colour)
    link(sigma, absorb.inputs["Density"])
    link(colour, emit.inputs["Color"])
    link(sigma, emit.inputs["Strength"])
    link(absorb.outputs[0], add.inputs[0])
    link(emit.outputs[0], add.inputs[1])
    link(add.outputs[0], out.inputs["Volume"])
    return mat


def mesh_material(name: str, attribute: str) -> bpy.types.Material:
    """Emission of the vertex colours: unlit, so the image is invariant under configuration changes."""
    mat = bpy.data.materials.new(name)
    nt = _node_tree(mat)
    vc, emit, out = nt.nodes.new("ShaderNodeVertexColor"), nt.nodes.new("ShaderNodeEmission"), nt.nodes.new("ShaderNodeOutputMaterial")
    vc.layer_name = attribute
    nt.links.new(vc.outputs["Color"], emit.inputs["Color"])
    nt.links.new(emit.outputs[0], out.inputs["Surface"])
    return mat
