"""ROS 2 encoding without ROS: message types, CDR payloads, the ``.msg`` definitions relloc ships.

``relloc.ros.cdr`` decodes and encodes the hot messages straight from the bytes;
``relloc.ros.messages`` holds the typestore (with ``msg/`` registered) and the conversions between
ROS messages and relloc events. Sources, sinks and the live engine use them; they know no source.
"""
