"""Pose error metrics and reports."""
