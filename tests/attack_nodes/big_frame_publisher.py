#!/usr/bin/python3
"""An insider's rogue publisher on its own host, speaking ROS 1 by hand (no rospy).

It registers NODE as a publisher of TOPIC (std_msgs/String) with its host's master
(ROS_MASTER_URI: the insider's own interceptor, which holds a publish grant for it),
answers requestTopic with its TCPROS port, replies to a subscriber's header like a
publisher, then sends one frame whose length prefix declares DECLARED bytes followed
by SENT bytes of junk. Prints READY once registered, CONNECTED when a subscriber's
header arrived, SENT n when done (or CUT n when the other side closed first).
argv: NODE TOPIC DECLARED SENT
"""
import os
import socket
import struct
import sys
import threading
import xmlrpc.client
from xmlrpc.server import SimpleXMLRPCServer

node, topic, declared, sent = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"
host = os.environ.get("ROS_IP", "127.0.0.1")

tcpros = socket.socket()
tcpros.bind((host, 0))
tcpros.listen(4)
tport = tcpros.getsockname()[1]

api = SimpleXMLRPCServer((host, 0), logRequests=False, allow_none=True)
api.register_function(lambda caller, t, protocols: [1, "ok", ["TCPROS", host, tport]], "requestTopic")
api.register_function(lambda caller: [1, "", os.getpid()], "getPid")
api.register_function(lambda caller, t, pubs: [1, "", 0], "publisherUpdate")
threading.Thread(target=api.serve_forever, daemon=True).start()
uri = f"http://{host}:{api.server_address[1]}/"


def header(fields):
    body = b"".join(struct.pack("<I", len(f)) + f for f in (f"{k}={v}".encode() for k, v in fields.items()))
    return struct.pack("<I", len(body)) + body


master = xmlrpc.client.ServerProxy(os.environ["ROS_MASTER_URI"])
print("REGISTER", master.registerPublisher(node, topic, "std_msgs/String", uri), flush=True)
print("READY", flush=True)
conn, _ = tcpros.accept()
(length,) = struct.unpack("<I", conn.recv(4, socket.MSG_WAITALL))
conn.recv(length, socket.MSG_WAITALL)
print("CONNECTED", flush=True)
conn.sendall(header({"callerid": node, "md5sum": MD5, "type": "std_msgs/String", "topic": topic, "latching": "0",
                     "message_definition": "string data\n"}))
done = 0
try:
    conn.sendall(struct.pack("<I", declared))
    chunk = b"x" * 65536
    while done < sent:
        conn.sendall(chunk)
        done += len(chunk)
    print("SENT", done, flush=True)
except OSError:
    print("CUT", done, flush=True)
conn.close()
