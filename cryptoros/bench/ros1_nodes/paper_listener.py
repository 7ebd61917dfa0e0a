#!/usr/bin/python3
"""The paper's listener (section IV): subscribes TOPIC, exits after COUNT messages.
The benchmark times it from launch to exit, as the paper did with `time`.
argv: NAME TOPIC COUNT. Prints FIRST <monotonic> and DONE <received>."""
import sys
import threading
import time

import rospy
from std_msgs.msg import String

name, topic, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
got = [0]
done = threading.Event()


def callback(msg):
    got[0] += 1
    if got[0] == 1:
        print("FIRST", time.monotonic(), flush=True)
    if got[0] >= count:
        done.set()


rospy.init_node(name, disable_signals=True)
rospy.Subscriber(topic, String, callback, tcp_nodelay=True)
done.wait(count * 0.1 + 60)
print("DONE", got[0], time.monotonic(), flush=True)
rospy.signal_shutdown("done")
