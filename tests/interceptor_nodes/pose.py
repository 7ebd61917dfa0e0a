#!/usr/bin/python3
"""Unmodified rospy nodes for the monitor tests: a robot's pose on /r0/pose.

pub NODE KIND HZ SECONDS  publish geometry_msgs/PoseStamped at HZ for SECONDS (stamped
                          now). KIND: 'clean' drives a smooth circle at 0.3 m/s;
                          'spoof' jumps to random positions (a compromised driver);
                          'flood' is the clean circle, sent at HZ (a flood on a held grant)
sub NODE SECONDS          print 'GOT <publisher> <x>' per message for SECONDS
Prints READY once registered; every line is flushed.
"""
import math
import random
import sys
import time

import rospy
from geometry_msgs.msg import PoseStamped

mode, node = sys.argv[1], sys.argv[2]
rospy.init_node(node.lstrip("/"), disable_signals=True)
if mode == "pub":
    kind, hz, seconds = sys.argv[3], float(sys.argv[4]), float(sys.argv[5])
    pub = rospy.Publisher("/r0/pose", PoseStamped, queue_size=1000, tcp_nodelay=True)
    print("READY", flush=True)
    deadline = time.monotonic() + 10
    while pub.get_num_connections() < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    rng = random.Random(7)
    start = time.monotonic()
    sent = 0
    while time.monotonic() - start < seconds:
        t = time.monotonic() - start
        msg = PoseStamped()
        msg.header.stamp = rospy.Time.now()
        msg.header.frame_id = "map"
        if kind == "spoof":
            msg.pose.position.x, msg.pose.position.y = rng.uniform(-20, 20), rng.uniform(-20, 20)
        else:  # a circle of radius 2 m at 0.3 m/s
            msg.pose.position.x, msg.pose.position.y = 2 * math.cos(0.15 * t), 2 * math.sin(0.15 * t)
        msg.pose.orientation.w = 1.0
        pub.publish(msg)
        sent += 1
        time.sleep(max(0.0, start + sent / hz - time.monotonic()))
    print("SENT", sent, flush=True)
    time.sleep(0.5)
else:
    seconds = float(sys.argv[3])

    def cb(msg):
        print("GOT", msg._connection_header.get("callerid", "?"), round(msg.pose.position.x, 3), flush=True)

    rospy.Subscriber("/r0/pose", PoseStamped, cb, tcp_nodelay=True)
    print("READY", flush=True)
    time.sleep(seconds)
    print("END", flush=True)
