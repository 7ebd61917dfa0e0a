#!/usr/bin/python3
"""Benchmark worker on real rospy, driven line by line over stdin/stdout.

argv: ROLE (talk | listen)
talk:   advertises /bench_str (std_msgs/String) and /bench_img (sensor_msgs/Image),
        prints READY once both have a subscriber; for each stdin line
        "MODE N SIZE" sends N messages and prints SENT.
listen: subscribes both topics (tcp_nodelay); for each stdin line "MODE N SIZE"
        resets its counters, prints ARMED, and prints RESULT <json> once N messages
        arrived or after 3 s without progress.
MODE: latency (String carrying CLOCK_MONOTONIC ns, 1 kHz), small (String, as fast
as rospy goes, queue_size=None), image (sensor_msgs/Image of SIZE bytes).

Environment, for the fixed stunnel chain only:
  BENCH_TCPROS_PORT (talk)  the TCPROS port to listen on (stunnel server connects here)
  BENCH_VIA (listen)        host:port every TCPROS connection goes to instead of the
                            port the publisher named (the stunnel client's accept port)
"""
import json
import os
import sys
import threading
import time

import rospy
from sensor_msgs.msg import Image
from std_msgs.msg import String

role = sys.argv[1]
STALL = 3.0


def out(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


if role == "listen":
    via = os.environ.get("BENCH_VIA")
    if via:
        from rospy.impl import tcpros_base

        via_host, via_port = via.rsplit(":", 1)
        _connect = tcpros_base.TCPROSTransport.connect

        def connect(self, dest_addr, dest_port, endpoint_id, timeout=None):
            return _connect(self, via_host, int(via_port), endpoint_id, timeout)

        tcpros_base.TCPROSTransport.connect = connect

    st = {"mode": None, "n": 0, "want": 0, "t0": 0, "t1": 0, "bytes": 0, "lat": []}
    done = threading.Event()

    def on_msg(m, mode):
        now = time.monotonic_ns()
        if st["mode"] != mode:
            return
        if mode == "latency":
            st["lat"].append(now - int(m.data))
        elif mode == "image":
            st["bytes"] += len(m.data)
        if st["n"] == 0:
            st["t0"] = now
        st["t1"] = now
        st["n"] += 1
        if st["n"] >= st["want"]:
            done.set()

    def on_str(m):
        on_msg(m, "latency" if st["mode"] == "latency" else "small")

    rospy.init_node("bench_listener", disable_signals=True)
    rospy.Subscriber("/bench_str", String, on_str, tcp_nodelay=True, buff_size=1 << 24)
    rospy.Subscriber("/bench_img", Image, lambda m: on_msg(m, "image"), tcp_nodelay=True, buff_size=1 << 24)
    out("SUBSCRIBED")
    for line in sys.stdin:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "quit":
            break
        mode, n = parts[0], int(parts[1])
        done.clear()
        st.update(mode=None, n=0, want=n, t0=0, t1=0, bytes=0, lat=[])
        st["mode"] = mode
        out("ARMED")
        last, deadline = -1, time.monotonic() + 120
        while not done.wait(STALL) and time.monotonic() < deadline:
            if st["n"] == last:
                break
            last = st["n"]
        st["mode"] = None
        out("RESULT " + json.dumps({k: st[k] for k in ("n", "t0", "t1", "bytes", "lat")}))
else:
    rospy.init_node("bench_talker", disable_signals=True, tcpros_port=int(os.environ.get("BENCH_TCPROS_PORT", "0")))
    pub_str = rospy.Publisher("/bench_str", String, queue_size=None, tcp_nodelay=True)
    pub_img = rospy.Publisher("/bench_img", Image, queue_size=None, tcp_nodelay=True)
    deadline = time.monotonic() + 60
    while (pub_str.get_num_connections() < 1 or pub_img.get_num_connections() < 1) and time.monotonic() < deadline:
        time.sleep(0.01)
    if pub_str.get_num_connections() < 1 or pub_img.get_num_connections() < 1:
        out("TIMEOUT no subscriber")
        sys.exit(1)
    time.sleep(0.3)
    out("READY")
    for line in sys.stdin:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "quit":
            break
        mode, n, size = parts[0], int(parts[1]), int(parts[2])
        if mode == "latency":
            nxt = time.monotonic()
            for i in range(n):
                pub_str.publish(String(data=str(time.monotonic_ns())))
                nxt += 0.001
                d = nxt - time.monotonic()
                if d > 0:
                    time.sleep(d)
        elif mode == "small":
            for i in range(n):
                pub_str.publish(String(data="hello world %d" % i))
        else:
            payload = bytes(size)
            for i in range(n):
                pub_img.publish(Image(height=1, width=size, encoding="mono8", step=size, data=payload))
        out("SENT")
