"""Segmentation backends that turn camera and tactile images into object masks."""
