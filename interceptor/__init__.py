"""cryptoros-interceptor: the drop-in TLS/JWT proxy in front of unmodified ROS nodes.

Built in its own issue; this package is reserved for it.
"""
