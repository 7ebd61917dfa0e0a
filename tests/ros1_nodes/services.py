#!/usr/bin/python3
"""rospy services: 'serve [DELAY [SECONDS]]' offers /rospy_loggers (roscpp/GetLoggers) and prints
READY (each call prints CALLED, then waits DELAY seconds before it answers) for SECONDS (30);
'call NAME' calls our roscpp/GetLoggers service NAME and prints the loggers."""
import sys
import time

import rospy
from roscpp.msg import Logger
from roscpp.srv import GetLoggers, GetLoggersResponse

mode = sys.argv[1]
if mode == "serve":
    rospy.init_node("rospy_server", disable_signals=True)

    delay = float(sys.argv[2]) if len(sys.argv) > 2 else 0.0

    def handle(req):
        print("CALLED", flush=True)
        time.sleep(delay)
        return GetLoggersResponse(loggers=[Logger(name="rospy.server", level="debug"), Logger(name="x", level="warn")])

    rospy.Service("/rospy_loggers", GetLoggers, handle)
    print("READY", flush=True)
    rospy.sleep(float(sys.argv[3]) if len(sys.argv) > 3 else 30)
else:
    rospy.init_node("rospy_client", disable_signals=True)
    rospy.wait_for_service(sys.argv[2], timeout=10)
    proxy = rospy.ServiceProxy(sys.argv[2], GetLoggers)
    for _ in range(2):
        resp = proxy()
        print("LOGGERS", ",".join(f"{lg.name}={lg.level}" for lg in resp.loggers), flush=True)
