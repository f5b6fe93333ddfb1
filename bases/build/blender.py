"""Thin bpy helpers: arrays <-> Blender meshes, evaluated (modifier-applied) vertices per frame."""

import bpy
import numpy as np


def reset_scene(fps=24):
    """An empty scene (factory settings, no startup objects)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = fps
    return scene


def mesh_object(name, verts, faces=(), edges=(), collection=None):
    """New object holding a mesh made from arrays: verts (N, 3), faces (F, k) or edges (E, 2)."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, v)) for v in verts], [tuple(map(int, e)) for e in edges],
                   [tuple(map(int, f)) for f in faces])
    me.update()
    ob = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(ob)
    return ob


def mesh_arrays(mesh):
    """A bpy mesh -> verts (N, 3) float64, polygons as a list of vertex-index tuples."""
    v = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", v)
    return v.reshape(-1, 3), [tuple(p.vertices) for p in mesh.polygons]


def triangles(polygons, verts=None):
    """Polygons (quads or triangles) -> triangles (F, 3) int64, fans from each polygon's first vertex.

    With verts (N, 3), each quad is split along the diagonal whose worse triangle is the
    rounder (largest min of area / sum of squared edges), and the polygons are returned
    rotated accordingly (-> (triangles, polygons)): reuse those polygons without verts to
    split other poses of the same mesh identically.
    """
    if verts is not None:
        v = np.asarray(verts, dtype=np.float64)

        def roundness(a, b, c):
            area = np.linalg.norm(np.cross(v[b] - v[a], v[c] - v[a]))
            return area / (np.sum((v[b] - v[a]) ** 2) + np.sum((v[c] - v[b]) ** 2) + np.sum((v[a] - v[c]) ** 2))

        rotated = []
        for p in polygons:
            if len(p) == 4:
                a, b, c, d = p
                if min(roundness(b, c, d), roundness(b, d, a)) > min(roundness(a, b, c), roundness(a, c, d)):
                    p = (b, c, d, a)
            rotated.append(tuple(p))
        return triangles(rotated), rotated
    out = []
    for p in polygons:
        for k in range(1, len(p) - 1):
            out.append((p[0], p[k], p[k + 1]))
    return np.asarray(out, dtype=np.int64)


def evaluated_vertices(obj, depsgraph=None):
    """Vertices (N, 3) of an object with its modifiers and animation evaluated at the current frame."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        v = np.empty(len(me.vertices) * 3, dtype=np.float64)
        me.vertices.foreach_get("co", v)
    finally:
        ev.to_mesh_clear()
    return v.reshape(-1, 3)


def evaluated_mesh(obj):
    """(verts (N, 3), polygons) of an object with its modifiers evaluated."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        return mesh_arrays(me)
    finally:
        ev.to_mesh_clear()


def bake(obj, frames):
    """Evaluated vertices at each frame: -> (T, N, 3) (the registered 4D sequence of an animation)."""
    scene = bpy.context.scene
    out = []
    for fr in frames:
        scene.frame_set(int(fr))
        out.append(evaluated_vertices(obj))
    return np.stack(out)
