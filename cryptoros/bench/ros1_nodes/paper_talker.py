#!/usr/bin/python3
"""The paper's talker (section IV): once a subscriber is connected, publishes COUNT
std_msgs/String on TOPIC at 10 Hz (rospy.Rate), then stays until stopped.
argv: NAME TOPIC COUNT. Prints REGISTERED after advertising, SENT at the end."""
import sys
import time

import rospy
from std_msgs.msg import String

name, topic, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
rospy.init_node(name, disable_signals=True)
pub = rospy.Publisher(topic, String, queue_size=10)
print("REGISTERED", flush=True)
deadline = time.monotonic() + 60
while pub.get_num_connections() < 1 and time.monotonic() < deadline:
    time.sleep(0.01)
rate = rospy.Rate(10)
for i in range(count):
    pub.publish(String(data="hello world %d" % i))
    rate.sleep()
print("SENT", count, flush=True)
time.sleep(120)
