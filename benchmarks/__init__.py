"""Benchmarks, grouped by the claim they back (README.md is the index). Each is run from the repository root either
as ``python -m benchmarks.<group>.<name>`` or as ``python benchmarks/<group>/<name>.py``; none edits ``sys.path``:
``eligsir_o3d`` is the installed package (an editable install of this checkout, or ``PYTHONPATH=$PWD``)."""
