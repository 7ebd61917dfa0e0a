"""cryptoros: drop-in security for ROS robots.

This package is the shared core: protocol codecs, token claims and verification,
the policy decision, TLS context construction, configuration models and the error
family. Nothing in it runs an event loop; the daemons in ``authz_server`` and
``interceptor`` are thin asyncio edges over it.
"""

__version__ = "0.1.0"
