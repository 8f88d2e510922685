"""The propagation's CPU kernels. The operation itself is `cvqpg.optics.propagate_content` (the
pruned transforms); its reference is the full-grid `cvqpg.optics.propagate`."""
