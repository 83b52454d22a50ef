"""Reliability: repeatability, resumption after SIGKILL, the long fuzz run."""
