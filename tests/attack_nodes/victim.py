#!/usr/bin/python3
"""An unmodified rospy robot for the attack toolkit tests: its drivers and its control
loop in one node ``/victim``.

It publishes its genuine pose (x=1), laser scan (all ranges 1.0) and drive command
(linear.x=0.5) at 10 Hz on /victim/pose, /victim/scan, /victim/cmd_vel and subscribes
to the same topics, as a robot's controller and base would. Every message it receives
that is not its own genuine content is foreign: it prints ``FOREIGN <topic> <summary>``
(at most 5 per topic) and at the end, however its loop ended, ``COUNTS pose=N scan=N cmd=N``. A ``shutdown``
call prints ``SHUTDOWN <reason>``. Prints READY once registered; lines are flushed.
It runs for SECONDS, or with ``--until-stdin-closes`` until its stdin closes (the
caller's attacks are over), SECONDS at most.
argv: SECONDS [--until-stdin-closes]
"""
import sys
import threading
import time

import rospy
import rospy.core
from geometry_msgs.msg import PoseStamped, Twist
from sensor_msgs.msg import LaserScan

seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0
rospy.init_node("victim", disable_signals=True)
counts = {"pose": 0, "scan": 0, "cmd": 0}


def foreign(kind, summary):
    counts[kind] += 1
    if counts[kind] <= 5:
        print("FOREIGN", kind, summary, flush=True)


def on_pose(m):
    if m.pose.position.x != 1.0 or m.pose.position.y != 0.0:
        foreign("pose", "x=%.3f y=%.3f" % (m.pose.position.x, m.pose.position.y))


def on_scan(m):
    if any(r != 1.0 for r in m.ranges):
        foreign("scan", "ranges[:3]=%s" % (list(m.ranges[:3]),))


def on_cmd(m):
    if m.linear.x != 0.5:
        foreign("cmd", "linear.x=%.3f" % m.linear.x)


rospy.core.add_preshutdown_hook(lambda reason: print("SHUTDOWN", reason, flush=True))
pose_pub = rospy.Publisher("/victim/pose", PoseStamped, queue_size=10)
scan_pub = rospy.Publisher("/victim/scan", LaserScan, queue_size=10)
cmd_pub = rospy.Publisher("/victim/cmd_vel", Twist, queue_size=10)
rospy.Subscriber("/victim/pose", PoseStamped, on_pose)
rospy.Subscriber("/victim/scan", LaserScan, on_scan)
rospy.Subscriber("/victim/cmd_vel", Twist, on_cmd, queue_size=1000)
print("READY", flush=True)
done = threading.Event()
if "--until-stdin-closes" in sys.argv[2:]:
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
end = time.monotonic() + seconds
pose = PoseStamped()
pose.pose.position.x = 1.0
scan = LaserScan(ranges=[1.0] * 36, range_max=3.5)
cmd = Twist()
cmd.linear.x = 0.5
try:
    while time.monotonic() < end and not done.is_set() and not rospy.is_shutdown():
        try:
            pose_pub.publish(pose)
            scan_pub.publish(scan)
            cmd_pub.publish(cmd)
        except rospy.ROSException:  # shut down (by an attack) between the check and the publish
            break
        time.sleep(0.1)
finally:  # whatever ended the loop (rospy's publish can also raise ValueError while shutting down)
    print("COUNTS pose=%d scan=%d cmd=%d" % (counts["pose"], counts["scan"], counts["cmd"]), flush=True)
    print("END", flush=True)
