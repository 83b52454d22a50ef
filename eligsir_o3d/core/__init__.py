"""Core types every part of the mapper shares: the pinhole :class:`~.camera.Camera` and SE(3) helpers
(:mod:`.camera`), one RGB-D :class:`~.frame.Frame` (:mod:`.frame`), the Gaussian map (:mod:`.gaussians`) and the
voxel keys of the microcell grid (:mod:`.voxels`), the numba decorators (:mod:`.jit`) and when torch and numba
work on one thread or all (:mod:`.threads`). Import from the submodules; this package imports nothing."""
