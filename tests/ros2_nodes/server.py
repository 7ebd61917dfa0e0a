"""An unmodified rclpy service server (no cryptoros code): std_srvs/srv/SetBool on SERVICE."""

import sys

import rclpy
from std_srvs.srv import SetBool

rclpy.init()
node = rclpy.create_node(sys.argv[2] if len(sys.argv) > 2 else "flag_server")


def handle(request, response):
    response.success = True
    response.message = f"flag set to {request.data} by {node.get_name()}"
    print(f"CALLED {request.data}", flush=True)
    return response


node.create_service(SetBool, sys.argv[1], handle)
print("READY", flush=True)
rclpy.spin(node)
