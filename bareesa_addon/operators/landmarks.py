"""Add Landmarks: one named Empty per basis landmark on the selected scan, for the artist to place."""

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, StringProperty
from mathutils import Matrix

from .. import convert as cv
from .common import landmark_empties, load_basis, own_or_panel, refuse, select_only, settings

GUESSES = (
    ("ALIGN", "Pre-alignment", "Place them where the template's landmarks land after a quick pre-alignment of "
                               "the template onto the scan (any orientation; may be mirrored on symmetric shapes)"),
    ("BOUNDS", "Bounding Box", "Map the template's bounding box onto the scan's (for scans upright as the "
                               "template: Z up, facing -Y)"),
)
#: Empty size, as a share of the scan's bounding-box diagonal.
EMPTY_SIZE = 0.015


def landmark_collection(scan):
    """The collection '<scan> Landmarks' under the scan's collection (made when missing): -> Collection."""
    name = f"{scan.name} Landmarks"
    parent = scan.users_collection[0] if scan.users_collection else bpy.context.scene.collection
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
    if coll.name not in parent.children:
        parent.children.link(coll)
    return coll


def guessed_points(basis, verts, tris, guess):
    """First guesses of the basis' landmarks on a scan, in the scan's local frame: -> {name: (3,)}."""
    template_points = np.array([basis.template[i] for i in basis.landmarks.values()])
    if guess == "BOUNDS":
        lo_t, hi_t = basis.template.min(0), basis.template.max(0)
        lo_s, hi_s = verts.min(0), verts.max(0)
        points = lo_s + (template_points - lo_t) / np.maximum(hi_t - lo_t, 1e-12) * (hi_s - lo_s)
    else:
        from .. import solver

        prealign = solver.module("registration.prealign")
        transform = prealign.prealign_candidates(basis.template, basis.faces, verts, tris)[0].transform
        points = transform.invert(template_points)  # template frame -> scan frame
    return dict(zip(basis.landmarks, points))


class BAREESA_OT_add_landmarks(bpy.types.Operator):
    """Put one named Empty per landmark of the basis on the active scan (a first guess); drag them onto the
    scan (surface snapping) and press Register: visible ones pull the fit"""

    bl_idname = "bareesa.add_landmarks"
    bl_label = "Add Landmarks"
    bl_options = {"REGISTER", "UNDO"}

    basis: StringProperty(name="Basis", default="", description="Bundled name or .npz path (empty: the panel's)")
    guess: EnumProperty(name="First Guess", items=GUESSES, default="ALIGN")
    snap: BoolProperty(name="Surface Snapping", default=True,
                       description="Turn on snapping to faces, so that dragged landmarks stay on the scan")

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        if obj is None or obj.type != "MESH":
            return refuse(cls, "make a scan mesh the active object")
        return refuse(cls, "the active object is a registered result: select the scan it came from"
                      if cv.PROP_BASIS in obj else None)

    def execute(self, context):
        scan = context.active_object
        try:
            basis, _ = load_basis(own_or_panel(self, context, "basis"))
            if not basis.landmarks:
                raise cv.ConversionError(f"basis '{basis.name}' has no named landmarks (a user basis gets them "
                                         "with build-basis --landmarks)")
            have = {str(e[cv.PROP_LANDMARK]) for e in landmark_empties(scan)}
            missing = [n for n in basis.landmarks if n not in have]
            if not missing:
                self.report({"INFO"}, f"'{scan.name}' already has all {len(have)} landmarks of basis '{basis.name}'")
                return {"CANCELLED"}
            verts, tris = cv.evaluated_mesh(scan, context.evaluated_depsgraph_get())
            points = guessed_points(basis, verts, tris, self.guess)
        except Exception as err:
            from ..jobs import is_user_error

            if not is_user_error(err):
                raise
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        coll = landmark_collection(scan)
        size = EMPTY_SIZE * float(np.linalg.norm(verts.max(0) - verts.min(0)))
        made = []
        for name in missing:
            empty = bpy.data.objects.new(f"{scan.name}.{name}", None)
            empty.empty_display_type = "SPHERE"
            empty.empty_display_size = size
            empty.show_name = True
            empty[cv.PROP_LANDMARK] = name
            coll.objects.link(empty)
            empty.parent = scan
            empty.matrix_parent_inverse = Matrix.Identity(4)
            empty.location = tuple(float(c) for c in points[name])  # the scan's local frame
            made.append(empty)
        if self.snap:
            tools = context.scene.tool_settings
            tools.use_snap = True
            tools.snap_elements = {"FACE_PROJECT"}
        select_only(context, made)
        kept = f", kept the {len(have)} already there" if have else ""
        self.report({"INFO"}, f"added {len(made)} landmarks to '{scan.name}'{kept}: drag them onto the scan, "
                              f"hide or delete any that cannot be placed, then Register")
        return {"FINISHED"}
