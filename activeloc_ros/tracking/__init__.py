"""
Simulated active tracking (paper Sec. 4.1, Tables 1 and 3), ROS-free: a pybullet world
with walking people (`world.TrackingWorld`), its four scenes (`scenes`) and AD-VAT's reward
(`reward`). `bench tracking` runs the experiment; `closed_loop.run_episode` steps it.
"""
