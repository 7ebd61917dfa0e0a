"""ROS 1 wire layer: sans-IO codecs (TCPROS, XML-RPC), URI rewriting, message types,
an asyncio node client and an embedded master."""
