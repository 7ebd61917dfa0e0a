#!/usr/bin/python3
"""One unmodified rospy node of a small robot graph (tests/system/test_learning.py).

talker NAME TOPIC        publishes std_msgs/String 'n <seq>' at 10 Hz
listener NAME TOPIC      prints GOT <data> for every message
server NAME SERVICE      serves roscpp/GetLoggers; prints CALLED per call
client NAME SERVICE      calls it every 0.5 s; prints ANSWER <n> or FAIL <error>
params NAME KEY          writes KEY once, then reads it and its own ~rate every 0.5 s: PARAM <v> <rate>
Prints READY once set up; every line is flushed; runs until stopped.
"""
import sys
import time

import rospy
from roscpp.msg import Logger
from roscpp.srv import GetLoggers, GetLoggersResponse
from std_msgs.msg import String

mode, name = sys.argv[1], sys.argv[2]
rospy.init_node(name.lstrip("/"), disable_signals=True)
if mode == "talker":
    pub = rospy.Publisher(sys.argv[3], String, queue_size=10)
    print("READY", flush=True)
    seq = 0
    while True:
        pub.publish(String(data=f"n {seq}"))
        seq += 1
        time.sleep(0.1)
elif mode == "listener":
    rospy.Subscriber(sys.argv[3], String, lambda m: print("GOT", m.data, flush=True))
    print("READY", flush=True)
    while True:
        time.sleep(1)
elif mode == "server":
    def handle(_req):
        print("CALLED", flush=True)
        return GetLoggersResponse(loggers=[Logger(name="graph", level="info")])

    rospy.Service(sys.argv[3], GetLoggers, handle)
    print("READY", flush=True)
    while True:
        time.sleep(1)
elif mode == "client":
    print("READY", flush=True)
    while True:
        try:
            rospy.wait_for_service(sys.argv[3], timeout=2)
            answer = rospy.ServiceProxy(sys.argv[3], GetLoggers)()
            print("ANSWER", len(answer.loggers), flush=True)
        except Exception as exc:  # a refusal, a timeout: the node carries on, as robots do
            print("FAIL", type(exc).__name__, str(exc).splitlines()[0][:120] if str(exc) else "", flush=True)
        time.sleep(0.5)
elif mode == "params":
    key = sys.argv[3]
    try:
        rospy.set_param(key, 3)
        print("SET", key, flush=True)
    except Exception as exc:
        print("FAIL", type(exc).__name__, str(exc)[:120], flush=True)
    print("READY", flush=True)
    while True:
        try:
            print("PARAM", rospy.get_param(key), rospy.get_param("~rate", None), flush=True)
        except Exception as exc:
            print("FAIL", type(exc).__name__, str(exc)[:120], flush=True)
        time.sleep(0.5)
