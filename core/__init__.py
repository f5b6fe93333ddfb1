"""BaRe-ESA solver core: basis-restricted elastic shape analysis of surface meshes.

Pure Python on torch/scipy/numpy (pykeops where it pays); never imports bpy.
Modules follow the paper: geometry (discrete differential geometry), h2_metric
(the six-weight invariant H2 metric and path energy), varifold (the data term),
mesh (I/O, validation, normalisation), evaluation (metrics), cli (the command).
"""

__version__ = "0.1.0"
