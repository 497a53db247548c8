"""Pose particle filter on SE(3): motion model, likelihood, resampling (Algorithms 3-4)."""
