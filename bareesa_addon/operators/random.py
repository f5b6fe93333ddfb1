"""Generate Random Bodies (the retry policy is ``bareesa.workflows.sample_bodies``)."""

import math

import bpy
from bpy.props import IntProperty

from .. import convert as cv
from .. import solver
from ..jobs import SolveOperator, Task
from .common import (common_basis, is_registered, load_basis, new_collection, refuse, registered_code, select_only,
                     settings, solve_options, template_object, workflows)


class BAREESA_OT_generate_random(SolveOperator, bpy.types.Operator):
    """Random bodies (seeded) from the basis' distribution or one fitted to a collection, in a grid"""

    bl_idname = "bareesa.generate_random"
    bl_label = "Generate Random Bodies"

    @classmethod
    def poll(cls, context):
        s = context.scene.bareesa
        return refuse(cls, None if s.basis.strip() or s.fit_collection else "choose a basis in the Basis section")

    count: IntProperty(name="Count", default=0, min=0, description="0: the panel's count")
    seed: IntProperty(name="Seed", default=-1, min=-1, description="-1: the panel's seed")

    def prepare(self, context):
        s = settings(context)
        n = self.count or s.count
        seed = s.seed if self.seed < 0 else self.seed
        fit = s.fit_collection
        wf = workflows()
        if fit is not None:
            objects = [o for o in fit.all_objects if is_registered(o)]
            if len(objects) < 2:
                raise cv.ConversionError(f"collection '{fit.name}' holds {len(objects)} registered objects: "
                                         "fitting a distribution needs two or more")
            basis, ref = common_basis(context, objects)
            names = solver.field_names(basis)
            fit_inputs = [wf.KnownCode(registered_code(o, basis, names)) for o in objects]
        else:
            basis, ref = load_basis(s.basis)
            if not wf.stored_distribution(basis):
                raise cv.ConversionError(f"basis '{basis.name}' stores no distribution: choose a collection of "
                                         "registered objects to fit one")
            fit_inputs = None
        options, steps = solve_options(context, basis), s.shoot_steps
        cursor = context.scene.cursor.location.copy()

        def solve(callback, cancel):
            return wf.random_bodies(basis, n, seed, options, fit=fit_inputs, components=1, shoot_steps=steps,
                                    callback=callback, cancel=cancel)

        def apply(context, bodies):
            codes, replaced = bodies.codes, bodies.replaced
            cv.check_code(codes, "the random codes")
            coll = new_collection(context, f"{basis.name}_random_seed{seed}")
            extent = basis.template.max(0) - basis.template.min(0)
            cols = math.ceil(math.sqrt(n))
            made = []
            for i, code in enumerate(codes):
                obj = template_object(context, basis, ref, f"{basis.name}_random_{i:03d}", coll, code, hint=codes)
                obj.location = cursor + type(cursor)((1.3 * extent[0] * (i % cols), -1.3 * extent[1] * (i // cols),
                                                      0.0))
                made.append(obj)
            select_only(context, made)
            note = (f"; {replaced} draw{'s' * (replaced > 1)} could not be shot or creased a joint flat and were "
                    "replaced") if replaced else ""
            return f"{n} random bodies (seed {seed}) in collection '{coll.name}'{note}"

        return Task("random bodies", solve, apply)
