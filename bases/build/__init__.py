"""Builders of the bundled bases (``python -m bases.build``).

These scripts run inside Blender's Python (the ``bpy`` module): they model,
rig and animate procedural surfaces, bake the animation to registered 4D
sequences and hand plain arrays to ``core`` (which never imports bpy) to build,
fit and save each basis. Everything is generated from seeds; no mesh is read.
"""
