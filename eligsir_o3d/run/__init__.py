"""One offline run into a results folder: the pipeline (:mod:`.pipeline`, ``run_mapping``), the results writer
(:mod:`.results`), resume checks (:mod:`.resume`), the folder lock (:mod:`.lock`), staged outputs and periodic
checkpoints (:mod:`.outputs`), the rule for unusable frames (:mod:`.frame_faults`) and the live run from a camera
(:mod:`.live_run`). Import from the submodules."""
