"""Platforms: CUDA and aarch64 machines, recording containers, batch tasks on a local Ray."""
