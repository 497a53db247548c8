"""Simulator of visuo-tactile insertion episodes that writes ROS 2 MCAP logs with ground truth."""
