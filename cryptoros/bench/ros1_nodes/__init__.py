"""ROS 1 node scripts of ``cryptoros bench interceptor``.

``rospy_worker.py``, ``paper_talker.py`` and ``paper_listener.py`` run under Debian's
``/usr/bin/python3`` (rospy); they are files to execute, not modules to import.
"""
