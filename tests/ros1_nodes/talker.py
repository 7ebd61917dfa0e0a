#!/usr/bin/python3
"""rospy talker: publishes COUNT std_msgs/String 'msg I' on TOPIC once SUBS subscribers
are connected, then stays LINGER seconds (args: TOPIC COUNT [SUBS [LINGER]])."""
import sys

import rospy
from std_msgs.msg import String

topic, count = sys.argv[1], int(sys.argv[2])
subs = int(sys.argv[3]) if len(sys.argv) > 3 else 1
rospy.init_node("rospy_talker", disable_signals=True)
pub = rospy.Publisher(topic, String, queue_size=None, tcp_nodelay=True)
deadline = rospy.get_time() + 20
while pub.get_num_connections() < subs and rospy.get_time() < deadline:
    rospy.sleep(0.02)
rospy.sleep(0.2)
for i in range(count):
    pub.publish(String(data=f"msg {i}"))
print("SENT", count, flush=True)
rospy.sleep(float(sys.argv[4]) if len(sys.argv) > 4 else 1.0)
