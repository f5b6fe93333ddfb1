"""A coarse mesh of a basis' template: registration takes the path energy of its coarse levels on it.

Blender's Decimate modifier (edge collapse, symmetric about x = 0 like the templates) keeps RATIO of the
template's faces; each coarse vertex is then tied to the template's surface as a barycentric point of its
nearest template face (Blender's BVH tree), so the coarse mesh deforms with the template through the basis' own
fields. Stored as ``extras`` "coarse_faces", "coarse_corners", "coarse_weights" (``Basis.coarse_mesh``);
``python -m bases.build.coarse [NAME]`` writes it into a shipped basis (default human), and the human
build adds it too. Needs bpy (the ``[bases]`` extra).
"""

import sys

import numpy as np

#: Share of the template's faces the coarse mesh keeps: the `human` template's 12,548 faces -> 4,390
#: (mean edge 2.9 cm against sigma 4.8 cm at its finest coarse level; bench/README)
RATIO = 0.35


def decimated(template, faces, ratio=RATIO):
    """Blender's collapse decimation of a mesh, symmetric about x = 0: (N, 3), (F, 3) -> (verts (n, 3),
    triangles (f, 3) int64)."""
    import bpy

    from .blender import mesh_arrays, mesh_object, reset_scene, triangles

    reset_scene()
    obj = mesh_object("template", template, faces)
    mod = obj.modifiers.new("decimate", "DECIMATE")
    mod.decimate_type, mod.ratio, mod.use_collapse_triangulate = "COLLAPSE", float(ratio), True
    mod.use_symmetry, mod.symmetry_axis = True, "X"
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    try:
        verts, polygons = mesh_arrays(mesh)
    finally:
        evaluated.to_mesh_clear()
    return verts, triangles(polygons)


def coarse_extras(template, faces, ratio=RATIO):
    """The ``extras`` of a basis' coarse mesh: {"coarse_faces" (f, 3) int64, "coarse_corners" (n, 3) int64
    template vertices, "coarse_weights" (n, 3) float64 barycentric weights}, each decimated vertex
    (``decimated``) moved to its nearest point on the template's surface."""
    from .blender import nearest_barycentric

    verts, coarse_faces = decimated(template, faces, ratio)
    nearest, weights = nearest_barycentric(template, faces, verts)
    return {"coarse_faces": coarse_faces.astype(np.int64), "coarse_corners": np.asarray(faces)[nearest].astype(np.int64),
            "coarse_weights": weights}


def describe(extras):
    """What the card says of a coarse mesh (``provenance["coarse_mesh"]``)."""
    n_faces = len(extras["coarse_faces"])
    return (f"{n_faces} faces, Blender's collapse decimation of the template (ratio {RATIO}, symmetric in x), "
            "vertices tied to the template's surface (bases/build/coarse.py); the path energy of registration's "
            "coarse levels is taken on it")


def main(argv=None):
    """Write the coarse mesh into a shipped basis (its arrays and card), the rest unchanged."""
    from bareesa.basis_io import add_extras, load_basis, update_card

    name = (argv if argv is not None else sys.argv[1:] or ["human"])[0]
    basis = load_basis(name)
    extras = coarse_extras(basis.template, basis.faces)
    add_extras(name, **extras)
    update_card(name, provenance=basis.provenance | {"coarse_mesh": describe(extras)})
    print(f"{name}: coarse mesh of {len(extras['coarse_faces'])} faces, {len(extras['coarse_weights'])} vertices")
    return 0


if __name__ == "__main__":
    sys.exit(main())
