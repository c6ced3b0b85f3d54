"""Primitives used everywhere: image checks and loading, atomic files and versioned checkpoints."""
