"""Pure-numpy geometry: SE(3) poses on (..., 4, 4) arrays, cameras and projections."""
