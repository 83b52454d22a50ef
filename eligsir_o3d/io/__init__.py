"""Bytes on disk: atomic writes and the full-disk rule (:mod:`.atomic`), the standard 3DGS PLY (:mod:`.ply`) and the
checkpoint encoding of a Reconstructor's state (:mod:`.checkpoint`). Import from the submodules."""
