"""Quality: pose sources against the truth, pose refinement where the truth is known, the TSDF peer."""
