"""Offline training in numpy: preprocessing, model-based baseline, hierarchical MLPs."""
