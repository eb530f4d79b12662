"""ROS 2 interop: plug the engine into a ROS 2 graph and into rosbag2 recordings.

Three faces, one core:

* :mod:`vpengine.ros2.core` — :class:`~vpengine.ros2.core.Ros2Core`, the engine behind every face, with no
  middleware, built from parts that are tested without DDS: :mod:`~vpengine.ros2.messages` (message types, image
  decoding), :mod:`~vpengine.ros2.outputs` (the output topics of each head and their messages),
  :mod:`~vpengine.ros2.frames` (the frame-id -> input-header book: every output carries its input's stamp and
  frame_id), :mod:`~vpengine.ros2.control` (rate and priority commands, the control thread),
  :mod:`~vpengine.ros2.heads` (heads added and removed at run time, their thread and outcomes) and
  :mod:`~vpengine.ros2.diagnostics` (``/diagnostics`` content, rejection counting, the input link).
* :mod:`vpengine.ros2.bridge` — the core on CycloneDDS, speaking ROS 2's wire protocol (``rt/`` topic names,
  ``pkg::msg::dds_::Type_`` type names, XCDR1 little-endian CDR) so stock ROS 2 tools see a normal node's topics.
  No ROS 2 installation needed. ``vpengine ros2 --config ... --input-topic ...`` runs it.
* :mod:`vpengine.ros2.node` — the same core as an rclpy node, with services, for machines with ROS 2 installed.

Bags (rosbag2, sqlite3 and MCAP) go through :mod:`vpengine.io.bag`, which uses the same parts. See ``docs/ros2.md``.
"""
