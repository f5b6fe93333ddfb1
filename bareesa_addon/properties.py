"""Scene settings of the BaRe-ESA panel (``scene.bareesa``); they are saved with the .blend."""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import solver
from .preferences import user_bases_dir
from .solver import SCHEDULE_PRESETS

#: The Basis menu's entry for a file chosen with the file browser.
OTHER_BASIS = "__FILE__"
#: Blender keeps only pointers to the strings of dynamic enum items: they must outlive the callback.
_BASIS_ITEMS = []


def basis_items(_self, _context):
    """The Basis menu: bundled and user bases by name (their card's summary as tooltip), then a file."""
    try:
        catalogue = solver.basis_catalogue(user_bases_dir())
    except solver.DependencyError:
        catalogue = []
    items = [(name, name, summary, k) for k, (name, summary) in enumerate(catalogue)]
    items.append((OTHER_BASIS, "Other File...", "An .npz basis file, chosen below", len(items)))
    _BASIS_ITEMS[:] = items
    return _BASIS_ITEMS


def _get_basis_choice(self):
    items = basis_items(self, None)
    by_name = {item[0]: item[3] for item in items}
    return by_name.get(self.basis, by_name[OTHER_BASIS])


def _set_basis_choice(self, value):
    name = next((item[0] for item in basis_items(self, None) if item[3] == value), OTHER_BASIS)
    if name != OTHER_BASIS:
        self.basis = name
    elif self.basis_file:
        self.basis = self.basis_file


def _basis_file_chosen(self, _context):
    if self.basis_file:
        self.basis = self.basis_file

METRIC_PRESETS = (
    ("BASIS", "Basis", "The metric weights stored with the basis"),
    ("BODY", "Body", "The paper's body weights (1, 1000, 100, 1, 1, 1)"),
    ("FACE", "Face", "The paper's face weights (1, 10, 10, 10, 1, 1)"),
    ("CUSTOM", "Custom", "Six weights a0, a1, b1, c1, d1, a2"),
)

EXTRAPOLATE_SOURCES = (
    ("AUTO", "Auto", "Two objects when two are chosen or selected, else the active object's keyframes"),
    ("OBJECTS", "Two Objects", "From the start object to the end object"),
    ("KEYFRAMES", "Keyframes", "The last two shape-key keyframes of the active registered object"),
)


def _is_mesh(_self, obj):
    return obj.type == "MESH"


class BareEsaSettings(bpy.types.PropertyGroup):
    """Everything the panel's sections need; operators read it when their own arguments are empty."""

    # Basis
    basis: StringProperty(name="Basis", default="human",
                          description="A bundled basis name (human, deformables), a basis saved in the user's "
                                      "bases directory, or a path to an .npz basis file")
    basis_choice: EnumProperty(name="Basis", items=basis_items, get=_get_basis_choice, set=_set_basis_choice,
                               description="The basis to use: a bundled one, one you built, or a file")
    basis_file: StringProperty(name="File", subtype="FILE_PATH", default="", update=_basis_file_chosen,
                               description="An .npz basis file (when the Basis menu says Other File)")
    metric: EnumProperty(name="Metric", items=METRIC_PRESETS, default="BASIS",
                         description="Weights of the invariant H2 metric")
    metric_custom: StringProperty(name="Weights", default="1,1000,100,1,1,1",
                                  description="a0,a1,b1,c1,d1,a2 for the custom metric")
    # Register
    schedule: EnumProperty(name="Schedule", items=SCHEDULE_PRESETS, default="FAST",
                           description="Multiscale registration schedule (Fast: what the demo uses; Paper: slower, "
                                       "closer fits)")
    prealign: BoolProperty(name="Pre-align", default=True,
                           description="Find the scan's rotation, position and scale first (off: the scan is "
                                       "already in the template's frame)")
    pose_search: BoolProperty(name="Pose Search", default=True,
                              description="Try the basis' typical poses as starts (how a raised arm or a bent "
                                          "leg is found); off: only the pose the coarse levels reach")
    retry_poor_fits: BoolProperty(name="Retry Poor Fits", default=True,
                                  description="Register a fit far from the scan again from other alignments "
                                              "(most often a body registered facing backwards)")
    detail_layer: BoolProperty(name="Detail Layer", default=True,
                               description="After the basis fit, also fit the scan's own detail the basis cannot "
                                           "make: one 'Detail' shape key (0-1) on the registered object; off: "
                                           "the pure basis fit")
    registration_settings: StringProperty(name="Settings", default="",
                                          description="Further registration settings, KEY=VALUE separated by ';' "
                                                      "(e.g. poses.finalists=3; solve.memory=50): the names "
                                                      "'bareesa register --show-config' prints")
    mask_group: StringProperty(name="Ignore Group", default="bareesa_ignore",
                               description="Vertex group of a scan whose weights say what to ignore (1: ignore, "
                                           "e.g. a floor, a wall, supports, hair); scans without it are used whole")
    # Interpolate / extrapolate
    object_a: PointerProperty(name="From", type=bpy.types.Object, poll=_is_mesh,
                              description="Start of the path (empty: the selected object that is not active)")
    object_b: PointerProperty(name="To", type=bpy.types.Object, poll=_is_mesh,
                              description="End of the path (empty: the active object)")
    steps: IntProperty(name="Steps", default=8, min=2, max=100,
                       description="Time points of the geodesic solve (keyframes are resampled from it)")
    geodesic_iterations: IntProperty(name="Iterations", default=200, min=1, max=5000,
                                     description="Most L-BFGS iterations of a geodesic solve (fewer: faster, "
                                                 "less exact in-betweens)")
    use_frame_range: BoolProperty(name="Own Frame Range", default=False,
                                  description="Use the Start and End below instead of the scene's frame range")
    frame_start: IntProperty(name="Start", default=1, description="First frame (when Own Frame Range is on)")
    frame_end: IntProperty(name="End", default=25, description="Last frame (when Own Frame Range is on)")
    anchor: BoolProperty(name="Keep Body Planted", default=True,
                         description="Keep the body's unmoving part where the straight line between the ends puts it "
                                     "(the metric's L2 term otherwise lets the body sink when a limb moves)")
    extrapolate_source: EnumProperty(name="Direction From", items=EXTRAPOLATE_SOURCES, default="AUTO",
                                     description="What gives the direction the motion is continued in")
    make_collection: BoolProperty(name="Also as meshes", default=False,
                                  description="Also bake every frame of the path as a mesh in a new collection")
    extrapolate_steps: IntProperty(name="New steps", default=4, min=1, max=200,
                                   description="Number of geodesic steps to continue the motion by")
    extrapolate_spacing: IntProperty(name="Spacing", default=5, min=1,
                                     description="Frames between extrapolated keyframes (when two objects are used)")
    # Motion transfer
    motion_source: PointerProperty(name="Motion", type=bpy.types.Object, poll=_is_mesh,
                                   description="A mesh animated without armature (shape keys, mesh cache, ...)")
    motion_collection: PointerProperty(name="Frames", type=bpy.types.Collection,
                                       description="Or: an ordered collection of per-frame objects (sorted by name)")
    motion_target: PointerProperty(name="Identity", type=bpy.types.Object, poll=_is_mesh,
                                   description="The body that performs the motion (empty: the active object)")
    identity_group: StringProperty(name="Identity group", default="shape",
                                   description="Basis group holding identity (body shape) coefficients")
    # Random bodies
    count: IntProperty(name="Count", default=6, min=1, max=400)
    seed: IntProperty(name="Seed", default=0, min=0)
    fit_collection: PointerProperty(name="Fit to", type=bpy.types.Collection,
                                    description="Fit the distribution to these registered objects "
                                                "(empty: the basis' stored distribution)")
    shoot_steps: IntProperty(name="Shooting steps", default=6, min=1, max=50)
    # Build basis
    build_source: PointerProperty(name="Animated mesh", type=bpy.types.Object, poll=_is_mesh,
                                  description="Its frames in the frame range (any animation Blender evaluates); "
                                              "empty: the active object")
    build_collection: PointerProperty(name="Meshes", type=bpy.types.Collection,
                                      description="Or: a collection of same-topology meshes (sorted by name)")
    build_group: StringProperty(name="Group", default="pose")
    build_components: IntProperty(name="Components", default=10, min=1, max=500)
    build_name: StringProperty(name="Name", default="my_basis")
    # Distance
    distance_collection: PointerProperty(name="Collection", type=bpy.types.Collection,
                                         description="Pairwise distances of its registered objects, written to CSV")
    distance_csv: StringProperty(name="CSV", subtype="FILE_PATH", default="//bareesa_distances.csv")
    distance: FloatProperty(name="Distance", default=-1.0, precision=4,
                            description="Last geodesic distance computed (-1: none yet)")
    distance_pair: StringProperty(name="Pair", default="")


CLASSES = (BareEsaSettings,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.bareesa = PointerProperty(type=BareEsaSettings)


def unregister():
    del bpy.types.Scene.bareesa
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
