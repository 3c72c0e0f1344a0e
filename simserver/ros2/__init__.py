"""The car on ROS 2 topics through rmw_zenoh, with no ROS installation (issue 19).

ROS 2's Zenoh middleware (rmw_zenoh, ROS 2 Jazzy) carries every topic as a zenoh key
expression with a CDR payload and a small attachment, and announces every node,
publisher and subscription with a liveliness token. simserver already speaks zenoh, so a
process that writes those keys, payloads and tokens is a ROS 2 node as far as any other
node can tell: ``ros2 topic list``, ``ros2 topic echo`` and any stack (Nav2, Autoware,
research code) see the car and drive it.

- :mod:`simserver.ros2.wire`: the rmw_zenoh wire format (key expressions, attachment,
  liveliness tokens) and the message types (rosbags' Jazzy type store, plus
  ``ackermann_msgs``), with the table of topics this adapter speaks.
- :mod:`simserver.ros2.convert`: a VehicleState to ``nav_msgs/Odometry``,
  ``sensor_msgs/Imu``, ``tf2_msgs/TFMessage`` and ``sensor_msgs/JointState`` (REP 103 and
  REP 105 frames and units).
- :mod:`simserver.ros2.control`: speed and steering targets to pedals and steer (the
  documented speed controller).
- :mod:`simserver.ros2.adapter`: the process (``simserver ros2``), fed by the state topic
  like the viewer, never in the 1 kHz loop.

How to use it from a ROS 2 machine: ``docs/ros2.md``.
"""
