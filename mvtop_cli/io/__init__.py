"""MCAP logs in (topics -> typed observation frames) and out (pose tracks), meshes, result files."""
