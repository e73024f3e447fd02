"""
The ROS 2 side: the nodes (camera, perception, controller, arm, recorder) and what only
they use (typed parameters, QoS, message conversions, the lockstep clock). Everything they
compute comes from the ROS-free core beside this folder.
"""
