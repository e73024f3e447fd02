"""Perception: ImageNet encoders and the online predictive-learning surprise model (ROS-free)."""
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.model import PerceptionResult, SurpriseModel

__all__ = ['PerceptionConfig', 'PerceptionResult', 'SurpriseModel']
