#!/usr/bin/python3
"""rospy listener: prints each std_msgs/String it gets on TOPIC, exits after COUNT."""
import sys
import threading

import rospy
from std_msgs.msg import String

topic, count = sys.argv[1], int(sys.argv[2])
done = threading.Event()
got = []


def cb(msg):
    got.append(msg.data)
    print("GOT", msg.data, msg._connection_header.get("md5sum"), flush=True)
    if len(got) >= count:
        done.set()


rospy.init_node("rospy_listener", disable_signals=True)
rospy.Subscriber(topic, String, cb, tcp_nodelay=True)
print("READY", flush=True)
done.wait(30)
print("DONE", len(got), flush=True)
rospy.sleep(20)  # stay registered until the test stops us
