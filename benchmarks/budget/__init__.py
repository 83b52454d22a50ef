"""Budget: the cost model, real time under load, memory and latency over a long stream."""
