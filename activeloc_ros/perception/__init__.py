"""Perception: ImageNet encoders and the online predictive-learning surprise model (ROS-free)."""
