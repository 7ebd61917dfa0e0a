"""The ROS 1 role of the interceptor (this package): XML-RPC and TCPROS over the gateway.

Composed with :class:`~interceptor.gateway.Gateway`, which owns the public listener,
tokens, limits, cut-off and reload. This role serves the stream purposes

  ``master``  XML-RPC for the master this interceptor fronts (master role);
  ``node``    XML-RPC for one exported local node API;
  ``topic``/``service``  TCPROS for one exported local TCPROS server: the
  connection header is checked, then bytes are pumped,

and opens its own loopback listeners:

- **local master** (plain HTTP, node role): the ``ROS_MASTER_URI`` of this host's
  unmodified nodes. Calls are checked against this interceptor's own grants, their
  URIs exported, and forwarded over a tunnel to the master's interceptor.
- **relays** (created on demand): one per remote endpoint a local process was
  handed; each tunnels to the endpoint's owner.

Every decision is a pure function of :mod:`cryptoros.policy.ros1`; this module does
the I/O. Everything fails closed: a call or stream that cannot be decided is refused,
the log gets who, what and why, the peer gets an opaque denial.
"""

from interceptor.ros1.role import Ros1Role
from interceptor.ros1.tunnels import TunnelPool, XmlRpcTunnel
from interceptor.ros1.wire import read_xmlrpc

__all__ = ["Ros1Role", "TunnelPool", "XmlRpcTunnel", "read_xmlrpc"]
