"""Estimators that learn from quality maps: the eigen-space classifier and the Delta regression."""
