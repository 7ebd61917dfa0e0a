"""An unmodified rclpy service server (no cryptoros code): std_srvs/srv/SetBool on SERVICE.

    server.py SERVICE [NODE] [--hang]

``--hang``: a server that never answers (its first call holds it for good)."""

import sys
import threading

import rclpy
from std_srvs.srv import SetBool

args = [a for a in sys.argv[1:] if a != "--hang"]
rclpy.init()
node = rclpy.create_node(args[1] if len(args) > 1 else "flag_server")


def handle(request, response):
    if "--hang" in sys.argv:
        print(f"HELD {request.data}", flush=True)
        threading.Event().wait()
    response.success = True
    response.message = f"flag set to {request.data} by {node.get_name()}"
    print(f"CALLED {request.data}", flush=True)
    return response


node.create_service(SetBool, args[0], handle)
print("READY", flush=True)
rclpy.spin(node)
