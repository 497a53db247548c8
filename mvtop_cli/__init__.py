"""mvtop: visuo-tactile in-hand object pose estimation (M-VTOP) over ROS 2 MCAP logs."""

__version__ = "0.1.0"
