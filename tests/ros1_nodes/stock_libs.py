#!/usr/bin/python3
"""rospy nodes that use what stock libraries use, for tests/system/test_stock_tools.py.

  stock_libs.py probe NAME KEY SECONDS    has_param/get_param KEY at 5 Hz, logging each
                                          time; prints PROBE <has> <value> once, DONE
  stock_libs.py launched                  (started by roslaunch) prints its ~rate, ~gains
                                          and the topic 'chatter' resolves to, publishes it
  stock_libs.py action_server             actionlib SimpleActionServer on /move_base: READY
  stock_libs.py action_client             sends one goal to /move_base: RESULT <state>
  stock_libs.py dr_server                 dynamic_reconfigure server (TestConfig) as /dr_server: READY
  stock_libs.py dr_client                 sets /dr_server's int_ to 7: SET <int_ now>
"""

import sys

import rospy


def probe(name: str, key: str, seconds: float) -> None:
    rospy.init_node(name)
    rate = rospy.Rate(5)
    end = rospy.get_time() + seconds
    first = True
    while not rospy.is_shutdown() and rospy.get_time() < end:
        has = rospy.has_param(key)
        value = rospy.get_param(key, "unset-default")
        rospy.loginfo("probed %s", key)
        if first:
            print("PROBE", has, value, flush=True)
            first = False
        rate.sleep()
    print("DONE", flush=True)


def launched() -> None:
    from std_msgs.msg import String

    rospy.init_node("launched", anonymous=False)
    topic = rospy.resolve_name("chatter")
    print("PARAM", rospy.get_param("~rate", None), sorted(rospy.get_param("~gains", {}).items()), topic, flush=True)
    pub = rospy.Publisher("chatter", String, queue_size=10)
    rate = rospy.Rate(5)
    for _ in range(10):
        pub.publish(String(data="launched"))
        rate.sleep()


def action_server() -> None:
    import actionlib
    from move_base_msgs.msg import MoveBaseAction, MoveBaseResult

    rospy.init_node("action_server")
    server = actionlib.SimpleActionServer("/move_base", MoveBaseAction,
                                          lambda goal: server.set_succeeded(MoveBaseResult()), auto_start=False)
    server.start()  # has_param <action>/status_frequency: an error answer would raise here
    print("READY", flush=True)
    rospy.spin()


def action_client() -> None:
    import actionlib
    from move_base_msgs.msg import MoveBaseAction, MoveBaseGoal

    rospy.init_node("action_client")
    client = actionlib.SimpleActionClient("/move_base", MoveBaseAction)
    if not client.wait_for_server(rospy.Duration(30)):
        print("NO SERVER", flush=True)
        return
    client.send_goal(MoveBaseGoal())
    client.wait_for_result(rospy.Duration(30))
    print("RESULT", client.get_state(), flush=True)


def dr_server() -> None:
    from dynamic_reconfigure.cfg import TestConfig
    from dynamic_reconfigure.server import Server

    rospy.init_node("dr_server")
    Server(TestConfig, lambda config, level: config)
    print("READY", flush=True)
    rospy.spin()


def dr_client() -> None:
    import dynamic_reconfigure.client

    rospy.init_node("dr_client")
    client = dynamic_reconfigure.client.Client("/dr_server", timeout=30)
    print("SET", client.update_configuration({"int_": 7})["int_"], flush=True)


if __name__ == "__main__":
    role = sys.argv[1]
    if role == "probe":
        probe(sys.argv[2], sys.argv[3], float(sys.argv[4]))
    elif role == "launched":
        launched()
    elif role == "action_server":
        action_server()
    elif role == "dr_server":
        dr_server()
    elif role == "dr_client":
        dr_client()
    else:
        action_client()
