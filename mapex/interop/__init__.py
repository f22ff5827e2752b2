"""Bridges to the formats of outside tools: ROS 2 messages, Foxglove schemas, MCAP."""
