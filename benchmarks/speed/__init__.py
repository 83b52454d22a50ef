"""Speed: renderer and update times, CPU targets, CUDA host round trips (ratios measured side by side)."""
