"""The outside-tool bridges: processes that subscribe to `mapex/@v1/**` and translate what
they hear for other tools (a PNG/GIF viewer, the browser view, ROS 2 topics, MCAP files,
the Foxglove app). They only read the wire (services.keys, services.messages); nothing in
the core processes needs them, except `services.up`/`services.evaluate` starting them on
request (`outside_tools`). See docs/interop.md.
"""
