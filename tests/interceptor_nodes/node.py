#!/usr/bin/python3
"""An unmodified rospy node for the interceptor tests.

pub NODE TOPIC COUNT [HZ [LINGER]]  publish COUNT std_msgs/String 'secret-I' (at HZ, 0 = as fast
                                    as possible) once a subscriber is connected (or after 5 s)
sub NODE TOPIC [SECONDS]            print GOT <data> for every message, for SECONDS
Prints READY once registered; every line is flushed.
"""
import sys
import time

import rospy
from std_msgs.msg import String

mode, node, topic = sys.argv[1], sys.argv[2], sys.argv[3]
rospy.init_node(node.lstrip("/"), disable_signals=True)
if mode == "pub":
    count = int(sys.argv[4])
    hz = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
    linger = float(sys.argv[6]) if len(sys.argv) > 6 else 2.0
    pub = rospy.Publisher(topic, String, queue_size=None, tcp_nodelay=True)
    print("READY", flush=True)
    deadline = time.monotonic() + 5
    while pub.get_num_connections() < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    print("SUBSCRIBERS", pub.get_num_connections(), flush=True)
    time.sleep(0.2)
    for i in range(count):
        pub.publish(String(data=f"secret-{i}"))
        if hz:
            time.sleep(1.0 / hz)
    print("SENT", count, flush=True)
    time.sleep(linger)
else:
    seconds = float(sys.argv[4]) if len(sys.argv) > 4 else 30.0

    def cb(msg):
        print("GOT", msg.data, flush=True)

    rospy.Subscriber(topic, String, cb, tcp_nodelay=True)
    print("READY", flush=True)
    time.sleep(seconds)
    print("END", flush=True)
