"""The runtime monitor: catches a publisher that abuses a grant it holds.

Authorization keeps out strangers and insiders without a grant; it cannot tell a
compromised robot's messages on a topic it may publish from honest ones. The monitor
looks at the messages themselves, per publisher and topic:

* :mod:`cryptoros.monitor.features`: sans-IO. One :class:`~.features.StreamFeatures`
  per (publisher, topic) turns each message body and its arrival time into a few
  numbers: for any type its rate and size; for the types it knows (poses, laser
  scans, velocity commands) what the content says (implied speed, scan roughness,
  time stamps running backwards or far behind).
* :mod:`cryptoros.monitor.model`: the detector. Per kind of topic, an upper limit per
  feature fitted on clean recordings (a high quantile with a margin), and a message
  scored by how far its worst feature exceeds its limit; an alert when enough messages
  in a row exceed. Fitted by ``cryptoros monitor train``, a JSON file the interceptor
  loads.

The interceptor's ``[monitor]`` section (``interceptor/monitor.py``) taps the bytes a
peer's publisher sends into the host, scores them off the forwarding path, and logs,
counts and optionally quarantines the offender.
"""
