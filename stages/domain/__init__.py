"""The pure domain layer: types and small functions that everything else shares.

No I/O, no HDF5, no printing, no jax/torch.  ``stages/{sim,subspace,render,vision}`` import
from here; ``stages/artefacts.py`` and ``stages/capture.py`` only read and write these types.

- :mod:`stages.domain.errors`    — RslError and the domain errors
- :mod:`stages.domain.rotations` — quaternion (w, x, y, z) / matrix / rotation-vector / slerp
- :mod:`stages.domain.cameras`   — the pinhole :class:`Camera`
- :mod:`stages.domain.controls`  — poses, tracks, selections, handles, loads, obstacles, controls
"""
