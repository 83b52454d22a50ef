"""``python -m eligsir_o3d.cli ...`` runs the ``eligsir`` command line."""

from .app import main

main()
