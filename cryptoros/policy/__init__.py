"""Policy decisions: a verified token's grants x a request -> allow, or
:class:`~cryptoros.errors.PolicyDenied` with a reason code.

Pure functions, no I/O, no clock: the interceptor's roles ask, then act.

- :mod:`cryptoros.policy.ros1`: master and node XML-RPC calls, parameters, TCPROS and
  service connection headers;
- :mod:`cryptoros.policy.ros2`: what a robot offers its peers from its DDS graph, and
  what a receiving robot accepts;
- :mod:`cryptoros.policy.infrastructure`: the one allowlist of what ROS itself uses on
  a node's behalf (logging, parameter and logger services), for both ROS versions.
"""
