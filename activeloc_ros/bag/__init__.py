"""
MCAP bags, no ROS install needed: `read` (facts, image topic, messages), `write`
(rosbag2 bags with their metadata) and `recover` (`reindex` a bag whose writer died).
`python -m activeloc_ros.bag --help` prints a bag's facts or mends one.
"""
