"""Sawyer arm over Zenoh with ROS 2 messages (CDR via rosbags)."""
