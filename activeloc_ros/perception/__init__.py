"""Perception: ImageNet encoders and the online predictive-learning surprise model (ROS-free)."""
from activeloc_ros.perception.model import PerceptionConfig, PerceptionResult, SurpriseModel

__all__ = ['PerceptionConfig', 'PerceptionResult', 'SurpriseModel']
