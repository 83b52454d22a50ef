#!/usr/bin/env python3
"""Shim over the CLI: ``python tools/export.py MAP.ply --mesh mesh.ply --point-cloud cloud.ply`` runs
``eligsir export MAP.ply --mesh mesh.ply --point-cloud cloud.ply`` (same options; ``--help`` lists them)."""

import sys

from eligsir_o3d.cli.app import main

if __name__ == "__main__":
    sys.argv = [sys.argv[0], "export", *sys.argv[1:]]
    main()
